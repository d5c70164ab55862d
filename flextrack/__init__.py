"""flextrack: flexible-frame-rate vision-aided inertial object tracking.

This package holds what every part shares and nothing heavy: the generated wire code
(`flextrack.v1`), the one implementation of the geometry and metrics (`flextrack.geometry`) and
the `flextrack` command line. It imports numpy, grpcio and protobuf at most.
"""

__version__ = "0.1.0"
