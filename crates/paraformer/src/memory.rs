//! Memory guard: what a match or an extraction needs, and the limit it is checked against
//! before anything large is allocated (a refused call returns [`Error::Resource`]
//! instead of aborting the process on a failed allocation).

use std::sync::atomic::{AtomicU64, Ordering};

use crate::config::Config;
use crate::error::{Error, Result};

/// 0 = derive the limit from the memory available when a call starts.
static LIMIT: AtomicU64 = AtomicU64::new(0);

/// Sets the process-wide memory limit in bytes (`None`: 90% of the memory available at
/// each call, the default). [`crate::MatchOptions::memory_limit`] overrides it per call.
pub fn set_memory_limit(bytes: Option<u64>) {
    LIMIT.store(bytes.unwrap_or(0).max(u64::from(bytes.is_some())), Ordering::Relaxed);
}

/// The limit in force: the one set, else 90% of the available memory (Linux
/// `MemAvailable`, capped by a cgroup limit), else no limit where neither can be read.
pub fn memory_limit() -> u64 {
    match LIMIT.load(Ordering::Relaxed) {
        0 => available_memory().map_or(u64::MAX, |a| a / 10 * 9),
        set => set,
    }
}

/// Memory available to this process in bytes, where the system tells.
pub fn available_memory() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let kb = meminfo.lines().find_map(|l| l.strip_prefix("MemAvailable:"))?.trim().trim_end_matches("kB").trim();
    let avail = kb.parse::<u64>().ok()?.saturating_mul(1024);
    let cgroup = std::fs::read_to_string("/sys/fs/cgroup/memory.max")
        .ok()
        .and_then(|s| s.trim().parse::<u64>().ok())
        .zip(std::fs::read_to_string("/sys/fs/cgroup/memory.current").ok().and_then(|s| s.trim().parse::<u64>().ok()))
        .map(|(max, cur)| max.saturating_sub(cur));
    Some(cgroup.map_or(avail, |c| c.min(avail)))
}

/// Bytes one match of `m` × `n` keypoints needs at its peak: the `[M+1, N+1]` couplings
/// and the Sinkhorn kernel of the same size, the per-task attention score blocks and
/// the activations (a slight over-estimate, never an under-estimate of the large parts).
pub fn match_bytes(config: &Config, m: usize, n: usize, threads: usize) -> u64 {
    // Saturating: a count too large to hold must fail the limit, not wrap below it.
    let (m, n) = (m as u64, n as u64);
    let cells = m.saturating_add(1).saturating_mul(n.saturating_add(1));
    let widest_stage = match config.model {
        crate::config::ModelKind::ParaformerU => config.stage_dims.iter().copied().max().unwrap_or(0),
        _ => 0,
    };
    let width = config.model_dim().max(widest_stage).max(config.descriptor_dim) as u64;
    let blocks = (threads.max(1) as u64 * 128).saturating_mul(m.max(n));
    let activations = m.saturating_add(n).saturating_mul(width * 24);
    cells.saturating_mul(2).saturating_add(blocks).saturating_add(activations).saturating_mul(4)
}

/// Bytes XFeat needs for a `width` × `height` image: the widest full- and half-resolution
/// feature maps with their im2col buffers, the heatmaps and the decoded image.
pub fn xfeat_bytes(width: usize, height: usize) -> u64 {
    (width as u64).saturating_mul(height as u64).saturating_mul(4 * 48)
}

/// `Ok` when `needed` fits `limit`, else [`Error::Resource`] naming `what`.
pub fn check(what: impl Into<String>, needed: u64, limit: u64) -> Result<()> {
    if needed <= limit {
        Ok(())
    } else {
        Err(Error::Resource { what: what.into(), needed, limit })
    }
}

/// Bytes in a short human form (`14.4 GB`).
pub fn human(bytes: u64) -> String {
    let b = bytes as f64;
    match b {
        _ if b >= 1e9 => format!("{:.1} GB", b / 1e9),
        _ if b >= 1e6 => format!("{:.1} MB", b / 1e6),
        _ => format!("{bytes} B"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_and_checks() {
        let cfg = Config::paraformer();
        let small = match_bytes(&cfg, 2048, 2048, 2);
        assert!(small > 2 * 2049 * 2049 * 4 && small < 200_000_000, "{small}");
        assert!(match_bytes(&cfg, 60_000, 60_000, 2) > 28_000_000_000);
        assert!(check("a match", 10, 10).is_ok());
        let e = check("a match of 60000 × 60000 keypoints", 28_800_000_000, 1_000_000_000).unwrap_err();
        assert!(e.to_string().contains("28.8 GB") && e.to_string().contains("1.0 GB"), "{e}");
        assert!(memory_limit() > 0);
    }
}
