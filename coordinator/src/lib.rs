//! The coordinator: accepts jobs, cuts them into work units, leases units to
//! workers, validates and merges their results into frames, writes images,
//! and keeps every accepted job and finished unit in a redb database so a
//! restart resumes where it stopped.
//!
//! Map: [`units`] (how a job is cut), [`farm`] (scheduling state, leases,
//! results), [`rate`] (measured rates and ETAs), [`store`] (durable state), [`service`] (gRPC edge), [`monitor`] (the web monitor), [`status_json`] (a job's JSON as `tessera status --json` prints it), [`metrics`] (Prometheus `/metrics`), [`notify`] (job-end notifications), [`edge`] (connection limits of both ports), [`server`]
//! (serving, health, reflection, periodic tasks). Images are written by
//! [`tracer_core::film::image`].

pub mod assets;
pub mod cost;
pub mod edge;
pub mod farm;
pub mod metrics;
pub mod monitor;
pub mod notify;
pub mod rate;
pub mod server;
pub mod service;
pub mod status_json;
pub mod store;
pub mod units;

pub use farm::{Config, Farm, FarmError};
