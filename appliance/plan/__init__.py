"""Planning the acquisition: optics, exposure, trigger spacing, and pacing them live.

What lives here: thin-lens optics and the image scale (`optics`), the exposure planner that
bounds motion blur and frame-to-frame motion (`exposure`), the trigger plan in
microcontroller ticks or encoder counts (`trigger_plan`), and the pacer that re-plans
exposure and trigger spacing as the crosshead speed changes during a test (`pacing`).

May import: `appliance.config`, `appliance.errors`, `hal` protocols. Not the loop, the
outputs or any device backend.
"""
