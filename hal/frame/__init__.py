"""Tensile frame controllers: the `TensileFrame` protocol and the backends behind it."""

from hal.frame.base import FrameState, TensileFrame

__all__ = ["FrameState", "TensileFrame"]
