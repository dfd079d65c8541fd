"""Bus helpers: the key space, codecs with validation, sessions, queues, presence and health.

Algorithms never import this package; services wire it to them.
"""

# The range checks of the message types with physical limits register themselves with the codec when
# imported: importing them here means any use of the bus package validates (codec <- validators, no
# import circle).
from shared.bus import validators as _validators  # noqa: F401
