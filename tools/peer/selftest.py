#!/usr/bin/env python3
"""Self-test for check_mcap.py, without the Rust tool.

Writes a small MCAP with mcap_ros2.writer.Writer (an Imu-like schema with a
nested std_msgs/Header, and a custom one with float32[], int16[] and uint8[]
arrays), writes the dump.jsonl that `gprflow inspect --dump-json` would
write for it, and runs check_mcap.py on the pair: it must pass.  Then it
breaks the pair in several ways (one corrupted value, a missing field, an
extra field, a missing line, a non-cdr channel, bad arguments) and checks
that each is caught with the expected exit status.

Usage:  .venv-peers/bin/python tools/peer/selftest.py
Exit:   0 when every case behaves, 1 otherwise.
"""

import copy
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

from mcap.writer import Writer as McapWriter
from mcap_ros2.writer import Writer

CHECK = Path(__file__).with_name("check_mcap.py")
SEP = "=" * 80 + "\n"

IMU_SCHEMA = (
    "std_msgs/Header header\n"
    "geometry_msgs/Quaternion orientation\n"
    "float64[9] orientation_covariance\n"
    "geometry_msgs/Vector3 angular_velocity\n"
    "float64[9] angular_velocity_covariance\n"
    "geometry_msgs/Vector3 linear_acceleration\n"
    "float64[9] linear_acceleration_covariance\n"
    + SEP + "MSG: std_msgs/Header\n"
    "builtin_interfaces/Time stamp\n"
    "string frame_id\n"
    + SEP + "MSG: geometry_msgs/Quaternion\n"
    "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
    + SEP + "MSG: geometry_msgs/Vector3\n"
    "float64 x\nfloat64 y\nfloat64 z\n"
)

SCAN_SCHEMA = (
    "std_msgs/Header header\n"
    "uint16 channel\n"
    "bool valid\n"
    "int64 offset_ns\n"
    "uint64 counter\n"
    "float32[] samples_f32\n"
    "int16[] samples_i16\n"
    "uint8[] raw\n"
    "float64[3] position\n"
    + SEP + "MSG: std_msgs/Header\n"
    "builtin_interfaces/Time stamp\n"
    "string frame_id\n"
)


def header(sec, nanosec, frame):
    return {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame}


def imu(i):
    return {
        "header": header(1700000000 + i, 250_000_000 * i, "imu_link"),
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.38268343, "w": 0.9238795},
        "orientation_covariance": [0.01 * k for k in range(9)],
        "angular_velocity": {"x": 1e-300, "y": -0.5, "z": math.nan},
        "angular_velocity_covariance": [-1.0] + [0.0] * 8,
        "linear_acceleration": {"x": 0.1, "y": 9.80665, "z": math.inf},
        "linear_acceleration_covariance": [1.0 / 3.0] * 9,
    }


def scan(i):
    return {
        "header": header(1700000000 + i, 999_999_999, "gpr_ch%d" % i),
        "channel": 65535 - i,
        "valid": i % 2 == 0,
        "offset_ns": -(2**63) + i,
        "counter": 2**64 - 1 - i,
        # float32: shortest reprs, float32 max, NaN, the smallest subnormal
        "samples_f32": [0.1, -2.5, 3.4028235e38, math.nan, 1e-45][: i + 3],
        "samples_i16": [-32768, 0, 32767, i],
        "raw": [0, 1, 127, 128, 255, i],
        "position": [1.5, -2.25, 1e10 + i],
    }


def jsonable(value):
    """What our dump writes: NaN/inf as null, containers recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [jsonable(v) for v in value]
    return value


def write_pair(directory):
    """Writes test.mcap and its dump.jsonl; returns their paths."""
    mcap_path, dump_path = directory / "test.mcap", directory / "dump.jsonl"
    entries = []
    with open(mcap_path, "wb") as stream:
        writer = Writer(stream, chunk_size=512)  # several chunks
        schemas = {
            "sensor_msgs/msg/Imu": writer.register_msgdef(
                "sensor_msgs/msg/Imu", IMU_SCHEMA),
            "gprflow_msgs/msg/Scan": writer.register_msgdef(
                "gprflow_msgs/msg/Scan", SCAN_SCHEMA),
        }
        for i in range(6):
            # log_time is deliberately not monotonic: the dump is file order
            for topic, name, make, log_time in (
                ("/imu", "sensor_msgs/msg/Imu", imu, 1000 + 10 * i),
                ("/gpr/scan", "gprflow_msgs/msg/Scan", scan, 995 + 10 * i),
            ):
                message = make(i)
                writer.write_message(topic, schemas[name], message,
                                     log_time=log_time, sequence=i)
                entries.append({"topic": topic, "sequence": i,
                                "log_time": log_time, "schema": name,
                                "message": jsonable(message)})
        writer.finish()
    write_dump(dump_path, entries)
    return mcap_path, dump_path, entries


def write_dump(path, entries):
    with open(path, "w", encoding="utf-8") as out:
        for entry in entries:
            out.write(json.dumps(entry, allow_nan=False) + "\n")


def write_json_channel(path):
    """An MCAP whose only channel is json-encoded: must be rejected."""
    with open(path, "wb") as stream:
        writer = McapWriter(stream)
        writer.start()
        schema = writer.register_schema("pkg/msg/T", "jsonschema", b"{}")
        channel = writer.register_channel("/j", "json", schema)
        writer.add_message(channel, log_time=1, publish_time=1, data=b"{}")
        writer.finish()


def run_check(*args):
    proc = subprocess.run([sys.executable, str(CHECK), *map(str, args)],
                          capture_output=True, text=True)
    return proc.returncode, proc.stdout + proc.stderr


def main():
    failures = 0
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        mcap_path, dump_path, entries = write_pair(tmp)

        def expect(name, want_rc, want_text, *args):
            nonlocal failures
            rc, output = run_check(*args)
            ok = rc == want_rc and want_text in output
            failures += not ok
            print(f"[{'ok' if ok else 'FAIL'}] {name}: exit {rc}")
            print("    " + output.strip().replace("\n", "\n    "))

        expect("clean pair", 0, "12 messages on 2 topics", mcap_path,
               dump_path)

        broken = tmp / "broken.jsonl"
        cases = [
            ("corrupted value", 1, "linear_acceleration.y",
             lambda e: e[2]["message"]["linear_acceleration"].update(y=9.8)),
            ("float32 off by 1 ulp", 1, "samples_f32[0]: dump=0.10000001",
             lambda e: e[1]["message"]["samples_f32"].__setitem__(
                 0, 0.10000001)),
            ("missing field", 1, "header.frame_id: dump=<missing>",
             lambda e: e[3]["message"]["header"].pop("frame_id")),
            ("extra field", 1, "samples_f32_extra",
             lambda e: e[5]["message"].update(samples_f32_extra=[])),
            ("missing line", 1, "<end of dump>", lambda e: e.pop()),
        ]
        for name, rc, text, mutate in cases:
            changed = copy.deepcopy(entries)
            mutate(changed)
            write_dump(broken, changed)
            expect(name, rc, text, mcap_path, broken)

        json_mcap = tmp / "json.mcap"
        write_json_channel(json_mcap)
        write_dump(broken, [{"topic": "/j", "sequence": 0, "log_time": 1,
                             "schema": "pkg/msg/T", "message": {}}])
        expect("json channel", 1, "(want 'cdr')", json_mcap, broken)
        expect("not an mcap", 2, "not an MCAP file", dump_path, dump_path)
        expect("usage", 2, "usage:", mcap_path)
    print("selftest:", "FAILED" if failures else "all cases behaved")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
