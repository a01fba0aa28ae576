"""Reading a Flock of Birds over a serial line: the wire format, link, reader thread, recordings.

Everything here turns bytes into frames (times, rotations, positions, valid) in SI units.
"""

from flockcal.lazy import public_api

# What a user of the driver reaches for, each loaded on first use (tests/test_public_api.py resolves them).
__getattr__, __dir__, __all__ = public_api(__name__, {
    "TrackerReader": "flockcal.drivers.reader",
    "TrackerConfig": "flockcal.drivers.reader",
    "TrackerEvent": "flockcal.drivers.reader",
    "FlockLink": "flockcal.drivers.link",
    "TrackerError": "flockcal.drivers.link",
    "FrameAssembler": "flockcal.drivers.assembly",
    "StreamDecoder": "flockcal.drivers.stream",
    "RecordFormat": "flockcal.drivers.records",
    "RecordingWriter": "flockcal.drivers.recording",
    "Recording": "flockcal.drivers.recording",
    "read_recording": "flockcal.drivers.recording",
    "replay": "flockcal.drivers.recording",
    "RecordingError": "flockcal.drivers.recording",
})
