"""The simulated world: specimen, materials, crosshead and camera physics behind the sim devices.

The hal simulators (`hal.camera.sim`, `hal.machine.sim`) own device behaviour (triggering, noise,
the controller interface); this package owns what they observe, and reaches them as objects
passed through the backend registry.
"""
