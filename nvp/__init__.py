"""nvp: Neural Voice Puppetry — audio-driven facial reenactment.

Nothing is done at import time; heavy modules are imported by the functions that need them.
"""

__version__ = "0.1.0"
