import sys

from services.watchdog.main import cli

sys.exit(cli())
