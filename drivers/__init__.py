"""Reading a Flock of Birds over a serial line: the wire format, link, reader thread, recordings.

Everything here turns bytes into frames (times, rotations, positions, valid) in SI units.
"""
