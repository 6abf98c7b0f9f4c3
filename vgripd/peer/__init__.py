"""The wire without the wire: the rules and byte formats every link speaks, with no I/O.

Everything in this room takes bytes, words or events and returns bytes, words or decisions; it
opens no socket, starts no task and reads no clock of its own (time is passed in). Link drivers
(``drivers/links/``) and the service are the shells around it: they own the sockets, the tasks
and the logging. So the rules can be tested like a pure function, by property tests over event
sequences, and the same rules serve every link kind.
"""
