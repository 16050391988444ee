"""Testing machine controllers: the `TestingMachine` protocol and the backends behind it."""

from hal.machine.base import MachineState, TestingMachine

__all__ = ["MachineState", "TestingMachine"]
