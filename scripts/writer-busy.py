#!/usr/bin/env python3
"""The coordinator's store writer per 1080p job, from a coordinator log at
debug level (RUST_LOG=tessera_coordinator=debug): from the job's
acceptance to its frame's completion, how long the one writer thread was
busy (every commit's time and every sync's), how many megabytes of films
went through the database, and the intake's decode and merge times
summed over its results (they run in parallel, so sums can exceed the
span). Usage: writer-busy.py COORDINATOR.log..."""
import datetime
import re
import sys


def ts(line):
    return datetime.datetime.fromisoformat(line[:26]).timestamp()


for path in sys.argv[1:]:
    print('==', path.split('/')[-1])
    lines = [l for l in open(path) if re.match(r'\d{4}-\d\d-\d\dT', l)]
    jobs = []
    for l in lines:
        if 'job accepted' in l and 'width=1920' in l:
            jobs.append([ts(l), None])
        if 'frame complete' in l and jobs and jobs[-1][1] is None:
            jobs[-1][1] = ts(l)
    for start, end in jobs:
        if end is None:
            continue
        busy = film_bytes = commits = syncs = decode = merge = 0
        for l in lines:
            if not start <= ts(l) <= end + 0.03:
                continue
            if 'store: commit ' in l:
                busy += float(re.search(r'commit_ms=([\d.]+)', l).group(1))
                film_bytes += int(re.search(r'film_bytes=(\d+)', l).group(1))
                commits += 1
            m = re.search(r'sync_ms=([\d.]+)', l)
            if m:
                busy += float(m.group(1))
                syncs += 1
            m = re.search(r'decode_ms=([\d.]+)', l)
            if m:
                decode += float(m.group(1))
            m = re.search(r'merge_ms=([\d.]+)', l)
            if m:
                merge += float(m.group(1))
        print('job: accepted to frame complete %.0f ms; store writer busy %.0f ms '
              '(%d commits, %.1f MB of films, %d syncs); decode %.0f ms, merge %.0f ms (summed)'
              % (1000 * (end - start), busy, commits, film_bytes / 1e6, syncs, decode, merge))
