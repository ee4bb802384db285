"""Loopback stand-ins for hardware endpoints, shared by the unit tests and the hardware-in-the-loop tests."""
