//! The gRPC API between Tessera processes. Not written yet: see issue 5 (the farm).
