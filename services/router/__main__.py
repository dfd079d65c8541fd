import sys

from services.router.main import cli

sys.exit(cli())
