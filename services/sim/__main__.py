import sys

from services.sim.main import cli

sys.exit(cli())
