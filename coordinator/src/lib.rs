//! The coordinator: accepts jobs, leases work units to workers, stitches frames. Not written yet: see issue 5 (the farm).
