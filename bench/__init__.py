"""Benchmarks and campaigns: the flight software, the simulator and the ground tools measured together."""
