"""Hardware errors, organised by the phase in which they happen.

Every backend raises these and only these, so the appliance can react by phase: a
configuration error is the user's to fix, a connection error may clear on retry, a timeout is
one missed frame or reply, and a device fault means the device itself reported a failure.
Messages are one line and name the device (its URL) and the setting or operation at fault.
"""


class HardwareError(Exception):
    """Base of all hardware errors."""


class HardwareConfigError(HardwareError):
    """A setting the device or the backend cannot accept (unknown URL, value out of range)."""


class HardwareConnectError(HardwareError):
    """The device cannot be reached or opened, or the connection was lost."""


class HardwareTimeout(HardwareError):
    """An operation did not complete within its timeout (no frame, no reply)."""


class HardwareFault(HardwareError):
    """The device reported a failure, or the backend found it in an inconsistent state."""
