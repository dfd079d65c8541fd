import sys

from services.coordinator.main import cli

sys.exit(cli())
