import sys

from services.mec.main import cli

sys.exit(cli())
