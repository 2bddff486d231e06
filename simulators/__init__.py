"""Simulated rig: device backends that speak the real protocols on loopback and ptys."""
