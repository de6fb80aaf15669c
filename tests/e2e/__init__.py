"""End-to-end tests of the capture path with real processes: the sim rig, faults."""
