"""What watches and drives a running test from outside the appliance.

What lives here: the Modbus register map (`modbus_map`) and the strain server for the
machine's controller (`modbus_server`), the Rerun viewer (`viewer`), the service manager's
notifications and watchdog (`sd_notify`), and the link that ties them to each test
(`link`).

May import: `appliance.run`, `appliance.measure`, `appliance.config`, `appliance.errors`.
Not the recording or the simulator.
"""
