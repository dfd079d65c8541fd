import sys

from services.recorder.main import cli

sys.exit(cli())
