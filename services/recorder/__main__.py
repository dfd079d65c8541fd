from services.recorder.main import cli
from shared.service import exit_process

exit_process(cli())
