"""The papers' experiments on the network-namespace testbed (`elasticfog bench ...`).

Every experiment runs the real daemons (`elasticfog registry|cloud|robot`) inside the hosts of a
`deploy.testbed.Testbed`: real TCP stacks, `tc` caps on the robot's uplink, a cgroup CPU quota on
the robot. `runner` brings a fleet up and always takes it down again; `fleet` writes the fleet
file whose endpoints are the testbed's addresses; `observer` is the small helper that watches the
fleet over Zenoh from a host of its own; `stats` turns the robot's telemetry into the tables'
figures; `table1`, `glitch` (and Table II), `table3`, `anycast` and `nav` (the navigation
assistant's Tables III-V: `nav_rows` its rows, `nav_loop` its closed loop) are the experiments,
and `report` renders markdown tables and PNG plots.
"""
