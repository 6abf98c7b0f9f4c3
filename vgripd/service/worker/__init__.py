"""The worker process and what runs in it: the process and its client, the shared-memory image
transport, camera supervision and the job recorder."""
