from services.city.main import cli
from shared.service import exit_process

exit_process(cli())
