//! The worker: registers with a coordinator, pulls work units, traces them. Not written yet: see issue 5 (the farm).
