"""The jobs the daemon runs: the job runner (trigger to answer), a finished job's record, the
conveyor recipes' belt lines, triggering by belt travel, and the walked hand-eye calibration
that takes the links and cameras over while it runs."""
