"""A simulated performer wearing tracker sensors, and a fake Flock of Birds on a pty or sim:// URL.

Importing this package registers the sim:// scheme with pyserial.
"""
