"""TopoCut: simulation, topology discovery, spectral reward and policy learning for multi-step cutting."""

__version__ = "0.1.0"
