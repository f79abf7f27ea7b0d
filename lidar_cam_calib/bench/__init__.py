"""Benchmarks: a simulator and a method side by side (a method never imports the simulator)."""
