import sys

from services.viewer.main import cli

sys.exit(cli())
