"""The daemon as a process on its host: background tasks, systemd notification, logging, the
heap after start-up, child processes (``vgripd`` commands, ending with the daemon), the one
transaction that writes the config file, and the commissioning checks. The bottom room of
service/: it imports no other room of it."""
