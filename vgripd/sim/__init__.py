"""Stand-ins for the other side of a link, for tests and the demo: mock PLC (Modbus client),
mock UR controller (RTDE server), mock robot Modbus server."""
