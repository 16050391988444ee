"""Hardware abstraction layer: cameras and testing machine controllers behind small protocols."""
