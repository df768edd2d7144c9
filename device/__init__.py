"""stereopath device side: capture, synchronisation, estimation, recording, streaming.

Importing this package has no side effects: no hardware, network or heavy
libraries are touched until a function that needs them is called.
"""

__version__ = "0.1.0"
