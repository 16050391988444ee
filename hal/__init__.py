"""Hardware abstraction layer: cameras and tensile frame controllers behind small protocols."""
