#!/usr/bin/env python3
"""The slowest tests of the last `cargo nextest run` (target/nextest/default/junit.xml), and the time per binary.

    python3 scripts/test_times.py [N]
"""
import collections
import pathlib
import sys
import xml.etree.ElementTree as ET

path = pathlib.Path(__file__).resolve().parent.parent / "target/nextest/default/junit.xml"
if not path.is_file():
    sys.exit(f"{path} is missing: run `make test` (or `cargo nextest run --workspace`) first")
n = int(sys.argv[1]) if len(sys.argv) > 1 else 25
cases = [(float(c.get("time", 0)), c.get("classname", "?"), c.get("name", "?")) for c in ET.parse(path).iter("testcase")]
per_binary = collections.Counter()
for t, binary, _ in cases:
    per_binary[binary] += t
print(f"{len(cases)} tests, {sum(t for t, _, _ in cases):.0f} s of test time")
print("\nslowest tests:")
for t, binary, name in sorted(cases, reverse=True)[:n]:
    print(f"{t:8.1f} s  {binary}  {name}")
print("\nslowest binaries:")
for binary, t in per_binary.most_common(n):
    print(f"{t:8.1f} s  {binary}")
