"""The toolkit's version, recorded in every stack and simulated dataset it writes."""

__version__ = "0.1.0"
