import sys

from services.device.main import cli

sys.exit(cli())
