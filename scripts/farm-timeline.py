#!/usr/bin/env python3
"""Timeline of a farm run from the workers' JSON debug logs, one file per
worker (bench-farm.sh keeps them as data-N.worker-I.log): per worker, when
it started and stopped rendering relative to the others, its busy time,
and the gaps between its units.

    scripts/farm-timeline.py LOG [LOG...]     (the logs of one run)
"""
import json, sys
from datetime import datetime


def ts(s):
    # tracing-subscriber's JSON timestamps: RFC 3339 with nanoseconds.
    s = s.rstrip("Z")
    if "." in s:
        head, frac = s.split(".")
        s = head + "." + frac[:6]
    return datetime.fromisoformat(s).timestamp()


units = {}
for path in sys.argv[1:]:
    for line in open(path, errors="replace"):
        try:
            ev = json.loads(line)
        except ValueError:
            continue
        f = ev.get("fields", {})
        if f.get("message") != "unit rendered":
            continue
        end = ts(ev["timestamp"])
        units.setdefault(path, []).append((end - float(f["seconds"]), end))
if not units:
    sys.exit("no 'unit rendered' events")
t0 = min(s for u in units.values() for s, _ in u)
t1 = max(e for u in units.values() for _, e in u)
total_busy = sum(e - s for u in units.values() for s, e in u)
print(f"{len(units)} worker(s), {sum(len(u) for u in units.values())} units, first start to last end {t1 - t0:.2f} s, "
      f"busy {100 * total_busy / (len(units) * (t1 - t0)):.1f}% of that")
for k, u in sorted(units.items()):
    u.sort()
    busy = sum(e - s for s, e in u)
    gaps = [b[0] - a[1] for a, b in zip(u, u[1:])]
    print(f"  {k}: {len(u)} units, busy {busy:.2f} s, starts +{u[0][0] - t0:.3f} s, ends -{t1 - u[-1][1]:.3f} s, "
          f"gaps {sum(gaps):.3f} s (max {max(gaps, default=0) * 1000:.1f} ms), mean unit {busy / len(u) * 1000:.1f} ms")
