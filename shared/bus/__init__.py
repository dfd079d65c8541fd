"""Bus helpers: the key space, codecs with validation, sessions, queues, presence and health.

Algorithms never import this package; services wire it to them.
"""
