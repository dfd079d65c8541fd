import sys

from services.sensor.main import cli

sys.exit(cli())
