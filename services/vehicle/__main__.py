import sys

from services.vehicle.main import cli

sys.exit(cli())
