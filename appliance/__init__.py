"""Video extensometer appliance: strain on a tensile specimen by digital image correlation."""

__version__ = "0.1.0"
