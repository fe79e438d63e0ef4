//! Rates measured over a sliding window, and the ETA that follows from one.
//!
//! A job's ETA is its *expected work still to do* (rays, from the cost
//! probe: [`crate::cost`]) over the rate at which expected work was done
//! lately. Counting in expected rays rather than pixel-samples matters
//! because pixels differ 150x in cost: tiles are leased in row order, so a
//! frame with sky on top and glass below runs fast and then slow, and a
//! samples-per-second ETA said 5 s at 27.9% and 20 s at 54.9% of a 61 s
//! job. The rate is recent (a window), not an average since the job or
//! the coordinator started: after a restart, or while no worker was
//! connected, the idle time before work resumed does not count (the
//! average since the start said 167 s and 501 s for that same job after a
//! restart).
//!
//! Times are seconds since an arbitrary origin, so the arithmetic is a pure
//! function of a recorded series ([`rate_over`], [`eta`]) and testable
//! without clocks.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// How far back a job's rate looks.
pub const JOB_WINDOW: Duration = Duration::from_secs(20);

/// The rate of work over the last `window` seconds of `points`, as of `now`.
///
/// `points` are (time, cumulative work), oldest first; the first is the
/// moment work began (cumulative 0 or whatever was done then). The rate is
/// the work done since the reference point over the time since it: the
/// reference is the last point at or before `now - window` (so a window
/// with few results still spans whole intervals between them), or the
/// first point when the series is younger than the window. `None` when no
/// work was done since the reference, or no time has passed.
pub fn rate_over(points: &[(f64, f64)], now: f64, window: f64) -> Option<f64> {
    let (&(t_last, w_last), _) = points.split_last()?;
    let start = now - window;
    let reference = points
        .iter()
        .rev()
        .find(|p| p.0 <= start)
        .unwrap_or(&points[0]);
    let work = w_last - reference.1;
    let secs = now.max(t_last) - reference.0;
    (work > 0.0 && secs > 0.0).then(|| work / secs)
}

/// Seconds left for `remaining` work at `rate` (None: unknown).
pub fn eta(remaining: f64, rate: Option<f64>) -> Option<f64> {
    let rate = rate.filter(|r| r.is_finite() && *r > 0.0)?;
    Some(remaining.max(0.0) / rate)
}

/// Cumulative work over time, trimmed to what [`rate_over`] can still use.
#[derive(Debug)]
pub struct Meter {
    origin: Instant,
    window: f64,
    points: VecDeque<(f64, f64)>,
    total: f64,
}

/// Closest spacing of a meter's points, in seconds.
const POINT_SPACING: f64 = 0.01;

impl Meter {
    pub fn new(window: Duration) -> Self {
        Meter {
            origin: Instant::now(),
            window: window.as_secs_f64(),
            points: VecDeque::new(),
            total: 0.0,
        }
    }

    fn secs(&self, t: Instant) -> f64 {
        t.saturating_duration_since(self.origin).as_secs_f64()
    }

    /// Work begins (again) at `t`: the rate counts from here, not from
    /// before. While work is under way (a result within the window) this
    /// changes nothing; after a longer pause (no worker, a restart) the
    /// series starts over, so the pause is not counted as slow work.
    pub fn start(&mut self, t: Instant) {
        let t = self.secs(t);
        if self.points.back().is_none_or(|p| t - p.0 > self.window) {
            self.points.clear();
            self.points.push_back((t, self.total));
        }
    }

    /// `work` more done at `t`.
    pub fn add(&mut self, t: Instant, work: f64) {
        let t = self.secs(t);
        if self.points.is_empty() {
            self.points.push_back((t, self.total));
        }
        self.total += work;
        // Points at most every POINT_SPACING seconds (the last one moves
        // forward instead): a farm accepting tens of thousands of results
        // a second keeps a few thousand points, not millions.
        let n = self.points.len();
        if n >= 2 && t - self.points[n - 2].0 < POINT_SPACING {
            self.points[n - 1] = (t, self.total);
        } else {
            self.points.push_back((t, self.total));
        }
        // Keep one point at or before the window's start (the reference)
        // and everything after it.
        let start = t - self.window;
        while self.points.len() > 2 && self.points[1].0 <= start {
            self.points.pop_front();
        }
    }

    /// The recent rate as of `now` (None: unknown).
    pub fn rate(&self, now: Instant) -> Option<f64> {
        let points: Vec<(f64, f64)> = self.points.iter().copied().collect();
        rate_over(&points, self.secs(now), self.window)
    }
}

/// How fast one worker renders: samples over busy seconds of its recent
/// results. The time between results (waiting for work, sending) is not
/// counted, so an idle worker keeps its speed instead of seeming slow, and
/// the window spans many units, so one costly tile does not make it look
/// ten times slower than an identical worker that drew sky.
#[derive(Debug, Default)]
pub struct WorkerSpeed {
    /// (when, pixel-samples, rays, render seconds), oldest first.
    recent: VecDeque<(Instant, u64, u64, f64)>,
}

/// The span of a worker's results its speed is measured over.
pub const WORKER_WINDOW: Duration = Duration::from_secs(20);
/// The fewest recent results kept whatever their age.
const WORKER_MIN_RESULTS: usize = 8;

impl WorkerSpeed {
    pub fn add(&mut self, t: Instant, samples: u64, rays: u64, seconds: f64) {
        self.recent.push_back((t, samples, rays, seconds));
        while self.recent.len() > WORKER_MIN_RESULTS
            && t.saturating_duration_since(self.recent[0].0) > WORKER_WINDOW
        {
            self.recent.pop_front();
        }
    }

    fn per_busy_second(&self, of: impl Fn(&(Instant, u64, u64, f64)) -> u64) -> f64 {
        let n: u64 = self.recent.iter().map(&of).sum();
        let seconds: f64 = self.recent.iter().map(|r| r.3).sum();
        if seconds > 0.0 {
            n as f64 / seconds
        } else {
            0.0
        }
    }

    /// Pixel-samples per busy second (0 before any result). Depends on
    /// which pixels the worker drew (they differ 150x in cost), so
    /// identical workers agree only over a mix of them.
    pub fn samples_per_second(&self) -> f64 {
        self.per_busy_second(|r| r.1)
    }

    /// Rays per busy second (0 before any result): about the same wherever
    /// in a frame they were traced.
    pub fn rays_per_second(&self) -> f64 {
        self.per_busy_second(|r| r.2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A job recorded as (time, cumulative expected work) at each result.
    /// The truth: how long the rest took.
    fn true_left(series: &[(f64, f64)], i: usize) -> f64 {
        series.last().unwrap().0 - series[i].0
    }

    #[test]
    fn rate_counts_from_the_reference_point_at_the_window_start() {
        let s = [(0.0, 0.0), (10.0, 100.0), (20.0, 300.0), (30.0, 600.0)];
        // Window 15 s at t=30: reference (10, 100): 500 work in 20 s.
        assert_eq!(rate_over(&s, 30.0, 15.0), Some(25.0));
        // Window 100 s: from the first point: 600 in 30 s.
        assert_eq!(rate_over(&s, 30.0, 100.0), Some(20.0));
        // 10 s after the last result, nothing new: the rate falls.
        assert_eq!(rate_over(&s, 40.0, 15.0), Some(300.0 / 20.0));
        // Nothing done since the reference: unknown.
        assert_eq!(rate_over(&s, 60.0, 15.0), None);
        assert_eq!(rate_over(&[(5.0, 0.0)], 6.0, 15.0), None);
        assert_eq!(rate_over(&[], 6.0, 15.0), None);
        assert_eq!(eta(50.0, Some(25.0)), Some(2.0));
        assert_eq!(eta(50.0, None), None);
        assert_eq!(eta(50.0, Some(0.0)), None);
    }

    /// The job: 61 s, fast tiles first (sky: 1 expected ray a
    /// sample), then costly ones (glass: 8), then fast again. Workers trace
    /// a steady 1000 rays/s of expected work. Samples per second swing 8x;
    /// expected rays per second do not, and neither does the ETA.
    #[test]
    fn eta_from_expected_work_holds_where_samples_mislead() {
        // (expected rays, samples) of each 1 s of rendering.
        let mut series = vec![(0.0, 0.0)];
        let mut samples = vec![(0.0, 0.0)];
        let (mut work, mut done) = (0.0, 0.0);
        for t in 1..=61 {
            let cost = if (20..45).contains(&t) { 8.0 } else { 1.0 };
            work += 1000.0;
            done += 1000.0 / cost;
            series.push((t as f64, work));
            samples.push((t as f64, done));
        }
        let (total_work, total_samples) = (work, done);
        for i in [5, 17, 25, 34, 44, 50] {
            let now = series[i].0;
            let left = total_work - series[i].1;
            let got = eta(left, rate_over(&series[..=i], now, 20.0)).unwrap();
            let truth = true_left(&series, i);
            assert!(
                (got - truth).abs() < 1e-9,
                "t={now}: eta {got} s, truth {truth} s"
            );
            // What a samples-per-second ETA since the start says at the
            // same moments: half the truth just before the glass (22 s
            // where 44 s are left).
            let s_left = total_samples - samples[i].1;
            let s_eta = eta(s_left, rate_over(&samples[..=i], now, 1e9)).unwrap();
            if i == 17 {
                assert!(s_eta < 0.55 * truth, "t={now}: {s_eta} vs {truth}");
            }
        }
    }

    /// A coordinator restarted at 30 s of a 61 s job: workers come back
    /// after 25 s of downtime and their first results arrive 1 s later.
    /// The meter starts when work is leased again, so the idle time is not
    /// counted; an average since the coordinator started (what the issue
    /// saw: 167 s and 501 s) would count it.
    #[test]
    fn eta_after_a_restart_ignores_the_time_before_work_resumed() {
        let origin = Instant::now();
        let at = |s: f64| origin + Duration::from_secs_f64(s);
        let mut m = Meter::new(JOB_WINDOW);
        let total = 61_000.0;
        let mut done = 30_000.0; // before the restart, recovered from the store
        // Restart at t=0; the first lease this run at t=25.
        m.start(at(25.0));
        for k in 1..=10 {
            let t = 25.0 + k as f64;
            done += 1000.0;
            m.add(at(t), 1000.0);
            let got = eta(total - done, m.rate(at(t))).unwrap();
            let truth = (total - done) / 1000.0;
            assert!((got - truth).abs() < 1e-6, "t={t}: {got} vs {truth}");
        }
        // All workers gone for a window: the rate, and so the ETA, is unknown.
        assert_eq!(m.rate(at(35.0 + 2.0 * JOB_WINDOW.as_secs_f64())), None);
        // Work leased again after the pause: it does not count.
        m.start(at(100.0));
        m.add(at(101.0), 500.0);
        assert_eq!(m.rate(at(101.0)), Some(500.0));
    }

    #[test]
    fn meter_keeps_only_what_the_window_needs() {
        let origin = Instant::now();
        let mut m = Meter::new(Duration::from_secs(10));
        for k in 0..1000 {
            m.add(origin + Duration::from_millis(100 * k), 1.0);
        }
        // 10 s of points at 10 a second, and the reference before them.
        assert!(m.points.len() <= 102, "{}", m.points.len());
        let r = m.rate(origin + Duration::from_millis(99_900)).unwrap();
        assert!((r - 10.0).abs() < 1e-9, "{r}");
        // 100 000 results in one second: points every 10 ms, same rate.
        let mut m = Meter::new(Duration::from_secs(10));
        for k in 0..100_000u64 {
            m.add(origin + Duration::from_micros(10 * k), 1.0);
        }
        assert!(m.points.len() <= 102, "{}", m.points.len());
        let r = m.rate(origin + Duration::from_secs(1)).unwrap();
        assert!((r - 100_000.0).abs() < 1_000.0, "{r}");
    }

    /// Two identical workers on a frame whose tiles differ 20x in cost
    /// (sky at 10 000 samples/s, glass at 500), each taking the next tile
    /// in row order when it is free, as leases go. The old measure (the
    /// last unit's speed, dropping at once) put them 20x apart whenever one
    /// had just finished glass and the other sky. Samples over busy time in
    /// a window keep them within 3x even at the sky-glass edges (where one
    /// has drawn a glass tile the other has not reached yet; 1x in steady
    /// state), and rays per busy second, which cost the same everywhere,
    /// agree to rounding.
    #[test]
    fn identical_workers_agree_whatever_their_last_tile() {
        let origin = Instant::now();
        let cost = |k: usize| {
            if (40..80).contains(&k) || k >= 150 {
                2.0
            } else {
                0.1
            }
        };
        let mut w = [WorkerSpeed::default(), WorkerSpeed::default()];
        let mut old = [0.0f64; 2];
        let mut free = [0.0f64; 2];
        let (mut worst_new, mut worst_old) = (1.0f64, 1.0f64);
        for k in 0..200 {
            let i = if free[0] <= free[1] { 0 } else { 1 };
            free[i] += cost(k);
            // Rays are proportional to time: 1000 rays a second.
            let rays = (1000.0 * cost(k)) as u64;
            w[i].add(
                origin + Duration::from_secs_f64(free[i]),
                1000,
                rays,
                cost(k),
            );
            let s = 1000.0 / cost(k);
            old[i] = if old[i] == 0.0 || s < old[i] {
                s
            } else {
                0.7 * old[i] + 0.3 * s
            };
            if k >= 2 {
                let (a, b) = (w[0].samples_per_second(), w[1].samples_per_second());
                worst_new = worst_new.max(a.max(b) / a.min(b));
                let (ra, rb) = (w[0].rays_per_second(), w[1].rays_per_second());
                assert!((ra - rb).abs() < 1e-9 * ra, "{ra} {rb}");
                worst_old = worst_old.max(old[0].max(old[1]) / old[0].min(old[1]));
            }
        }
        assert!(worst_old > 10.0, "{worst_old}");
        assert!(worst_new < 3.0, "{worst_new}");
        assert_eq!(WorkerSpeed::default().samples_per_second(), 0.0);
    }
}
