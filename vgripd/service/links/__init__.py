"""The robot links as the daemon sees them: the link contract (``RobotLink``, triggers, health),
what every link driver shares (health cell, outage policy, reconnect loop), the connection
manager of the server surfaces, rate-limited fault logging, the login throttle, the supervision
of the configured links, the web view's trigger link and the walked hand-eye exchange."""
