//! Placement (issue 38): workers' labels and jobs' requirements, the one
//! syntax both ends of the wire check (`tessera worker --label`, `tessera
//! submit --require`, the coordinator's register and submit).
//!
//! A label is `KEY=VALUE`; a requirement is `KEY=VALUE` (the label equals
//! the value) or `KEY>=N` (the label is a number at least N). A worker
//! meets a job when it meets every one of the job's requirements.

use std::collections::BTreeMap;
use std::fmt;

/// Most labels one worker carries, and most requirements of one job.
pub const MAX_LABELS: usize = 64;
/// Longest label value (and requirement value).
const MAX_VALUE_CHARS: usize = 200;

/// Labels every worker reports of itself: `backend` (cpu, gpu), `gpu`
/// (the adapter's name), `gpu_memory_gb`, `memory_gb` (the host's, whole
/// GiB), `cores` and `host`. The coordinator sets `backend` and `cores` from the worker's capabilities,
/// so they cannot be given by hand.
pub const AUTOMATIC_LABELS: [&str; 6] = [
    "backend",
    "gpu",
    "gpu_memory_gb",
    "memory_gb",
    "cores",
    "host",
];

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PlacementError {
    #[error(
        "{what} {text:?}: the key must be 1 to 63 letters, digits, '_', '-' or '.' (as in gpu_memory_gb)"
    )]
    BadKey { what: &'static str, text: String },
    #[error(
        "{what} {text:?}: the value must be printable text of at most {MAX_VALUE_CHARS} characters"
    )]
    BadValue { what: &'static str, text: String },
    #[error("label {0:?} is not KEY=VALUE")]
    NotALabel(String),
    #[error("requirement {0:?} is neither KEY=VALUE nor KEY>=N")]
    NotARequirement(String),
    #[error("requirement {text:?}: {n:?} is not a number")]
    NotANumber { text: String, n: String },
    #[error("more than {MAX_LABELS} {0}")]
    TooMany(&'static str),
}

fn check_key(what: &'static str, text: &str, key: &str) -> Result<(), PlacementError> {
    let ok = (1..=63).contains(&key.len())
        && key
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'));
    if ok {
        Ok(())
    } else {
        Err(PlacementError::BadKey {
            what,
            text: text.into(),
        })
    }
}

fn check_value(what: &'static str, text: &str, value: &str) -> Result<(), PlacementError> {
    if value.is_empty()
        || value.chars().count() > MAX_VALUE_CHARS
        || value.chars().any(char::is_control)
    {
        return Err(PlacementError::BadValue {
            what,
            text: text.into(),
        });
    }
    Ok(())
}

/// `KEY=VALUE` as `tessera worker --label` takes it.
pub fn parse_label(text: &str) -> Result<(String, String), PlacementError> {
    let (k, v) = text
        .split_once('=')
        .ok_or_else(|| PlacementError::NotALabel(text.into()))?;
    check_label(k, v)?;
    Ok((k.to_string(), v.to_string()))
}

/// A label's key and value, as the coordinator checks what a worker sends.
pub fn check_label(key: &str, value: &str) -> Result<(), PlacementError> {
    let text = format!("{key}={value}");
    check_key("label", &text, key)?;
    check_value("label", &text, value)
}

/// A set of labels as a worker sends it.
pub fn check_labels(labels: &BTreeMap<String, String>) -> Result<(), PlacementError> {
    if labels.len() > MAX_LABELS {
        return Err(PlacementError::TooMany("labels"));
    }
    labels.iter().try_for_each(|(k, v)| check_label(k, v))
}

/// One requirement of a job.
#[derive(Clone, Debug, PartialEq)]
pub enum Requirement {
    /// The label `key` is exactly this value.
    Equals { key: String, value: String },
    /// The label `key` is a number of at least this.
    AtLeast { key: String, min: f64 },
}

impl Requirement {
    /// `KEY=VALUE` or `KEY>=N`.
    pub fn parse(text: &str) -> Result<Requirement, PlacementError> {
        if let Some((k, n)) = text.split_once(">=") {
            check_key("requirement", text, k)?;
            let min = n
                .trim()
                .parse::<f64>()
                .ok()
                .filter(|m| m.is_finite())
                .ok_or_else(|| PlacementError::NotANumber {
                    text: text.into(),
                    n: n.into(),
                })?;
            return Ok(Requirement::AtLeast { key: k.into(), min });
        }
        let (k, v) = text
            .split_once('=')
            .ok_or_else(|| PlacementError::NotARequirement(text.into()))?;
        check_key("requirement", text, k)?;
        check_value("requirement", text, v)?;
        Ok(Requirement::Equals {
            key: k.into(),
            value: v.into(),
        })
    }

    /// A job's requirements as sent.
    pub fn parse_all(texts: &[String]) -> Result<Vec<Requirement>, PlacementError> {
        if texts.len() > MAX_LABELS {
            return Err(PlacementError::TooMany("requirements"));
        }
        texts.iter().map(|t| Requirement::parse(t)).collect()
    }

    /// Whether a worker with these labels meets it (a label it lacks, or a
    /// value that is not a number for `>=`, does not).
    pub fn met_by(&self, labels: &BTreeMap<String, String>) -> bool {
        match self {
            Requirement::Equals { key, value } => labels.get(key) == Some(value),
            Requirement::AtLeast { key, min } => labels
                .get(key)
                .and_then(|v| v.trim().parse::<f64>().ok())
                .is_some_and(|v| v >= *min),
        }
    }
}

/// Whether a worker with `labels` meets every one of `reqs`.
pub fn meets(reqs: &[Requirement], labels: &BTreeMap<String, String>) -> bool {
    reqs.iter().all(|r| r.met_by(labels))
}

impl fmt::Display for Requirement {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Requirement::Equals { key, value } => write!(f, "{key}={value}"),
            Requirement::AtLeast { key, min } => write!(f, "{key}>={min}"),
        }
    }
}

/// Where a unit goes after a failure that another worker may not have:
/// out of memory, or a lost GPU (issue 38). Held per unit by the
/// coordinator (not persisted: after a restart the unit may go anywhere
/// again) and checked beside its job's requirements.
#[derive(Clone, Debug, PartialEq)]
pub enum Reroute {
    /// Out of memory on a worker with `key` = `gb` (`gpu_memory_gb` on a
    /// GPU, `memory_gb` on a CPU): a worker with more of it, or, after a
    /// GPU's, a CPU worker (which the job's requirements may rule out).
    MoreMemory { key: &'static str, gb: f64 },
    /// A lost GPU: a CPU worker.
    OffGpu,
    /// Any worker but this session (what the failing one lacked is not
    /// known: no memory label, or the job must stay on a GPU).
    NotWorker(String),
}

impl Reroute {
    /// After an out-of-memory failure on worker session `worker` with
    /// `labels`.
    pub fn out_of_memory(worker: &str, labels: &BTreeMap<String, String>) -> Reroute {
        let key = if labels.get("backend").is_some_and(|b| b == "gpu") {
            "gpu_memory_gb"
        } else {
            "memory_gb"
        };
        match labels.get(key).and_then(|v| v.trim().parse::<f64>().ok()) {
            Some(gb) if gb.is_finite() => Reroute::MoreMemory { key, gb },
            _ => Reroute::NotWorker(worker.to_string()),
        }
    }

    /// After a lost GPU on worker session `worker` with `labels`, for a
    /// job with requirements `reqs`: the CPU unless they keep it off one.
    pub fn gpu_lost(
        worker: &str,
        labels: &BTreeMap<String, String>,
        reqs: &[Requirement],
    ) -> Reroute {
        let on_gpu = labels.get("backend").is_some_and(|b| b == "gpu");
        let cpu_allowed = !reqs.iter().any(|r| match r {
            Requirement::Equals { key, value } => {
                (key == "backend" && value != "cpu") || key == "gpu" || key == "gpu_memory_gb"
            }
            Requirement::AtLeast { key, .. } => key == "gpu_memory_gb",
        });
        if on_gpu && cpu_allowed {
            Reroute::OffGpu
        } else {
            Reroute::NotWorker(worker.to_string())
        }
    }

    /// Whether worker session `worker` with `labels` may take the unit.
    pub fn admits(&self, worker: &str, labels: &BTreeMap<String, String>) -> bool {
        let cpu = labels.get("backend").is_none_or(|b| b == "cpu");
        match self {
            Reroute::MoreMemory { key, gb } => {
                (*key == "gpu_memory_gb" && cpu)
                    || labels
                        .get(*key)
                        .and_then(|v| v.trim().parse::<f64>().ok())
                        .is_some_and(|m| m > *gb)
            }
            Reroute::OffGpu => cpu,
            Reroute::NotWorker(w) => w != worker,
        }
    }
}

impl fmt::Display for Reroute {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Reroute::MoreMemory {
                key: "gpu_memory_gb",
                gb,
            } => write!(
                f,
                "a GPU with more than {gb} GB (gpu_memory_gb) or a CPU worker"
            ),
            Reroute::MoreMemory { key, gb } => write!(f, "a worker with more than {gb} GB ({key})"),
            Reroute::OffGpu => write!(f, "a CPU worker"),
            Reroute::NotWorker(_) => write!(f, "another worker"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn labels(pairs: &[(&str, &str)]) -> BTreeMap<String, String> {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect()
    }

    #[test]
    fn requirements_parse_print_and_match() {
        let gpu = Requirement::parse("backend=gpu").unwrap();
        let mem = Requirement::parse("gpu_memory_gb>=40").unwrap();
        assert_eq!(gpu.to_string(), "backend=gpu");
        assert_eq!(mem.to_string(), "gpu_memory_gb>=40");
        let big = labels(&[("backend", "gpu"), ("gpu_memory_gb", "80")]);
        let small = labels(&[("backend", "gpu"), ("gpu_memory_gb", "24")]);
        let cpu = labels(&[("backend", "cpu")]);
        assert!(meets(&[gpu.clone(), mem.clone()], &big));
        assert!(!meets(&[gpu.clone(), mem.clone()], &small));
        assert!(!meets(&[gpu], &cpu));
        assert!(!meets(&[mem], &labels(&[("gpu_memory_gb", "lots")])));
        assert!(meets(&[], &cpu));
    }

    #[test]
    fn out_of_memory_and_lost_gpus_send_the_unit_where_it_can_run() {
        let g24 = labels(&[("backend", "gpu"), ("gpu_memory_gb", "24")]);
        let g80 = labels(&[("backend", "gpu"), ("gpu_memory_gb", "80")]);
        let gpu_unknown = labels(&[("backend", "gpu")]);
        let c64 = labels(&[("backend", "cpu"), ("memory_gb", "64")]);
        let c256 = labels(&[("backend", "cpu"), ("memory_gb", "256")]);
        // A GPU out of memory: a bigger GPU or a CPU, not a GPU of as much.
        let r = Reroute::out_of_memory("w1", &g24);
        assert_eq!(
            r.to_string(),
            "a GPU with more than 24 GB (gpu_memory_gb) or a CPU worker"
        );
        assert!(r.admits("w2", &g80) && r.admits("w3", &c64));
        assert!(!r.admits("w4", &g24) && !r.admits("w5", &gpu_unknown));
        // A CPU out of memory: a CPU with more memory only.
        let r = Reroute::out_of_memory("w1", &c64);
        assert!(r.admits("w2", &c256) && !r.admits("w3", &c64) && !r.admits("w4", &g80));
        // Memory unknown: anyone else.
        let r = Reroute::out_of_memory("w1", &gpu_unknown);
        assert_eq!(r, Reroute::NotWorker("w1".into()));
        assert!(r.admits("w2", &g24) && !r.admits("w1", &g80));
        // A lost GPU: the CPU where the job allows it, else another worker.
        let r = Reroute::gpu_lost("w1", &g80, &[]);
        assert!(r.admits("w2", &c64) && !r.admits("w3", &g80));
        for req in ["backend=gpu", "gpu_memory_gb>=40", "gpu=NVIDIA H200"] {
            let reqs = [Requirement::parse(req).unwrap()];
            let r = Reroute::gpu_lost("w1", &g80, &reqs);
            assert_eq!(r, Reroute::NotWorker("w1".into()), "{req}");
            assert!(r.admits("w2", &g24) && !r.admits("w1", &g80));
        }
    }

    #[test]
    fn bad_labels_and_requirements_are_refused_by_name() {
        assert_eq!(
            Requirement::parse("pool").unwrap_err().to_string(),
            "requirement \"pool\" is neither KEY=VALUE nor KEY>=N"
        );
        assert_eq!(
            Requirement::parse("cores>=many").unwrap_err().to_string(),
            "requirement \"cores>=many\": \"many\" is not a number"
        );
        assert!(matches!(
            Requirement::parse("po ol=night"),
            Err(PlacementError::BadKey { .. })
        ));
        assert_eq!(
            parse_label("pool").unwrap_err().to_string(),
            "label \"pool\" is not KEY=VALUE"
        );
        assert!(matches!(
            parse_label("pool=\u{1b}[2J"),
            Err(PlacementError::BadValue { .. })
        ));
        assert_eq!(
            parse_label("pool=night").unwrap(),
            ("pool".into(), "night".into())
        );
    }
}
