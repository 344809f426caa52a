#!/usr/bin/env python3
"""Peer check: does a trusted reader decode our MCAP files as we do?

Reads FILE.mcap with the reference Python reader (``mcap`` +
``mcap_ros2.decoder.DecoderFactory``) and compares every message, field by
field, with DUMP.jsonl as written by ``gprflow inspect FILE.mcap --dump-json``:
one JSON object per message, in file order, with keys ``topic``,
``sequence``, ``log_time``, ``schema`` and ``message``.

Rules: objects are compared by field name (both sides must have the same
fields), lists elementwise, ``uint8[]`` (``bytes`` in mcap_ros2) as lists of
ints, strings and integers exactly.  Floats are equal when both are
non-finite (NaN/inf on the ROS side, ``null`` in the dump), or when equal to
a relative 1e-12, or when the ROS value is a float32 and the dump holds a
decimal that rounds to it in float32 (the shortest float32 repr).  Every
channel must use ``cdr`` message encoding and a ``ros2msg`` schema.
Other top-level keys in a dump line (e.g. ``publish_time``) are ignored.

Usage:  check_mcap.py FILE.mcap DUMP.jsonl
Exit:   0 identical, 1 mismatches (first 20 printed), 2 usage/unreadable.
Run it with the venv made by tools/peer/setup-venv.sh.
"""

import json
import math
import struct
import sys
from types import SimpleNamespace

import mcap_ros2
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

MAX_SHOWN = 20
REL_TOL = 1e-12
HEADER_KEYS = ("topic", "sequence", "log_time", "schema")
MISSING = object()


class UsageError(Exception):
    """Bad arguments or an unreadable input: exit 2."""


class Undecodable:
    """Stands in for a message mcap_ros2 could not decode."""

    def __init__(self, reason):
        self.reason = reason


class TolerantFactory(DecoderFactory):
    """mcap_ros2's factory, but failures become Undecodable values.

    This keeps iter_decoded_messages going past one bad channel or message
    so that every problem is reported, not only the first.
    """

    def decoder_for(self, message_encoding, schema):
        try:
            decode = super().decoder_for(message_encoding, schema)
        except Exception as err:  # schema text mcap_ros2 cannot parse
            reason = f"schema not parsed: {type(err).__name__}: {err}"
            return lambda data: Undecodable(reason)
        if decode is None:
            reason = "no ros2msg/cdr decoder for this channel"
            return lambda data: Undecodable(reason)

        def tolerant(data):
            try:
                return decode(data)
            except Exception as err:  # truncated or malformed CDR
                reason = f"decode failed: {type(err).__name__}: {err}"
                return Undecodable(reason)

        return tolerant


class Report:
    """Counts mismatches and keeps the first MAX_SHOWN."""

    def __init__(self):
        self.count = 0
        self.shown = []

    def add(self, topic, sequence, path, ours, theirs):
        self.count += 1
        if len(self.shown) < MAX_SHOWN:
            self.shown.append((topic, sequence, path, ours, theirs))


def short(value, limit=100):
    """repr() of a value, cut to `limit` characters."""
    text = "<missing>" if value is MISSING else repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def as_float32(value):
    """`value` rounded to float32, or None when out of float32 range."""
    try:
        return struct.unpack("<f", struct.pack("<f", value))[0]
    except OverflowError:
        return None


def floats_equal(ours, theirs):
    """Float rule: see the module docstring."""
    if not math.isfinite(theirs):
        return ours is None
    if isinstance(ours, bool) or not isinstance(ours, (int, float)):
        return False
    if ours == theirs:
        return True
    if abs(ours - theirs) <= REL_TOL * max(abs(ours), abs(theirs)):
        return True
    return as_float32(theirs) == theirs and as_float32(ours) == theirs


def compare(ours, theirs, path, fail):
    """Compares one dump value with one mcap_ros2 value, recursively.

    `fail(path, ours, theirs)` is called for each difference.
    """
    if isinstance(theirs, (bytes, bytearray, memoryview)):
        theirs = list(bytes(theirs))
    if isinstance(theirs, SimpleNamespace):
        fields = list(type(theirs).__slots__)
        if not isinstance(ours, dict):
            fail(path, ours, f"<{type(theirs).__name__} object>")
            return
        for name in fields:
            sub = f"{path}.{name}" if path else name
            compare(ours.get(name, MISSING), getattr(theirs, name), sub, fail)
        for name in ours:
            if name not in fields:
                sub = f"{path}.{name}" if path else name
                fail(sub, ours[name], MISSING)
    elif ours is MISSING:
        fail(path, ours, theirs)
    elif isinstance(theirs, list):
        if not isinstance(ours, list):
            fail(path, ours, theirs)
        elif len(ours) != len(theirs):
            fail(f"{path} (length)", len(ours), len(theirs))
        else:
            for i, (a, b) in enumerate(zip(ours, theirs)):
                compare(a, b, f"{path}[{i}]", fail)
    elif isinstance(theirs, bool):
        if not (isinstance(ours, bool) and ours == theirs):
            fail(path, ours, theirs)
    elif isinstance(theirs, int):
        if type(ours) is not int or ours != theirs:
            fail(path, ours, theirs)
    elif isinstance(theirs, float):
        if not floats_equal(ours, theirs):
            fail(path, ours, theirs)
    elif isinstance(theirs, str):
        if not (isinstance(ours, str) and ours == theirs):
            fail(path, ours, theirs)
    else:
        fail(f"{path} (unexpected mcap_ros2 type {type(theirs).__name__})",
             ours, theirs)


def read_dump(path):
    """Yields (line number, object) for each non-blank line of the dump."""
    def reject_constant(name):
        raise ValueError(f"non-standard JSON constant {name}")

    try:
        handle = open(path, encoding="utf-8")
    except OSError as err:
        raise UsageError(f"cannot read dump {path}: {err}") from err
    with handle:
        for number, line in enumerate(handle, 1):
            if not line.strip():
                continue
            try:
                obj = json.loads(line, parse_constant=reject_constant)
            except ValueError as err:
                raise UsageError(f"{path}:{number}: not JSON: {err}") from err
            if not isinstance(obj, dict):
                raise UsageError(f"{path}:{number}: not a JSON object")
            yield number, obj


def check_channel(channel, schema, report):
    """Reports a channel that is not ros2msg schema + cdr encoding."""
    if channel.message_encoding != "cdr":
        report.add(channel.topic, "-", "<channel message_encoding>",
                   "(want 'cdr')", channel.message_encoding)
    encoding = schema.encoding if schema is not None else "<no schema>"
    if encoding != "ros2msg":
        report.add(channel.topic, "-", "<schema encoding>",
                   "(want 'ros2msg')", encoding)


def check(mcap_path, dump_path):
    """Runs the comparison; returns (report, message count, topics)."""
    report = Report()
    topics = set()
    seen_channels = set()
    dump = read_dump(dump_path)
    count = 0
    try:
        stream = open(mcap_path, "rb")
    except OSError as err:
        raise UsageError(f"cannot read {mcap_path}: {err}") from err
    with stream:
        try:
            reader = make_reader(stream, decoder_factories=[TolerantFactory()])
        except (McapError, ValueError) as err:
            raise UsageError(f"{mcap_path}: not an MCAP file: "
                             f"{type(err).__name__}: {err}") from err
        decoded = reader.iter_decoded_messages(log_time_order=False)
        try:
            for schema, channel, message, value in decoded:
                count += 1
                topics.add(channel.topic)
                if channel.id not in seen_channels:
                    seen_channels.add(channel.id)
                    check_channel(channel, schema, report)
                entry = next(dump, None)
                if entry is None:
                    report.add(channel.topic, message.sequence, "<dump>",
                               "<end of dump>", f"message #{count}")
                    continue
                compare_entry(entry, schema, channel, message, value, report)
        except McapError as err:
            report.add("-", "-", f"<mcap read error after {count} messages>",
                       "-", str(err))
    extra = [number for number, _ in dump]
    if extra:
        report.add("-", "-", f"<dump lines {extra[0]}..{extra[-1]}>",
                   f"{len(extra)} more line(s)", "<end of mcap>")
    return report, count, topics


def compare_entry(entry, schema, channel, message, value, report):
    """Compares one dump line with one decoded MCAP message."""
    number, ours = entry
    topic, sequence = channel.topic, message.sequence

    def fail(path, a, b):
        report.add(topic, sequence, path, a, b)

    theirs = {
        "topic": channel.topic,
        "sequence": message.sequence,
        "log_time": message.log_time,
        "schema": schema.name if schema is not None else "",
    }
    for key in HEADER_KEYS:
        compare(ours.get(key, MISSING), theirs[key], f"<{key}>", fail)
    if isinstance(value, Undecodable):
        fail("<message>", "(dump line %d)" % number, value.reason)
    else:
        compare(ours.get("message", MISSING), value, "", fail)


def main(argv):
    """Entry point; returns the exit status."""
    if len(argv) == 2 and argv[1] in ("-h", "--help"):
        print(__doc__.strip())
        return 0
    if len(argv) != 3:
        print("usage: check_mcap.py FILE.mcap DUMP.jsonl  (--help for more)",
              file=sys.stderr)
        return 2
    try:
        report, count, topics = check(argv[1], argv[2])
    except UsageError as err:
        print(f"peer check: error: {err}", file=sys.stderr)
        return 2
    if report.count:
        print(f"peer check: {report.count} mismatch(es) between {argv[1]} "
              f"(mcap_ros2 {mcap_ros2.__version__}) and {argv[2]}; "
              f"first {len(report.shown)}:")
        for topic, sequence, path, ours, theirs in report.shown:
            print(f"  {topic} seq={sequence} {path or '<message>'}: "
                  f"dump={short(ours)} mcap_ros2={short(theirs)}")
        return 1
    print(f"peer check: {count} messages on {len(topics)} topics decoded "
          f"identically by mcap_ros2 {mcap_ros2.__version__}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
