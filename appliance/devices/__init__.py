"""Glue between the hardware layer and a test: what a run needs of its devices beyond `hal`.

What lives here: the testing machine polled on its own thread (`polled_machine`), the
trigger microcontroller as the simulated camera's trigger line (`mcu_trigger`), and the
stamping of a real camera's frames with the times of the triggers that exposed them
(`trigger_stamping`).

May import: `appliance.plan`, `appliance.errors`, `hal`, `firmware_bridge`. Not the loop,
the outputs or the simulator.
"""
