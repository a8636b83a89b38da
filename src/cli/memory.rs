//! Memory: the big allocations of a run (its replay memory, or PQN's rollout) checked against
//! what this process may use, before any folder is made or written.

use anyhow::bail;

use invaders::dqn::Config;

/// What a run needs beside its replay memory: networks, optimizer state and batch buffers,
/// generously.
pub(super) const NETWORKS_BYTES: u64 = 512 << 20;

/// Refuses a run whose replay memory (or PQN rollout) needs more memory than this process may
/// use ([`usable_bytes`]): the allocation would fail (under `ulimit -v` or a cgroup's limit)
/// or the pages would run out when touched. Says how much it needs, and which limit is the
/// lowest.
pub(super) fn check_memory(config: &Config) -> anyhow::Result<()> {
    let need = config.replay_bytes() + NETWORKS_BYTES;
    let Some((have, which)) = usable_bytes() else {
        return Ok(());
    };
    if need <= have {
        return Ok(());
    }
    let gib = |b: u64| b as f64 / (1u64 << 30) as f64;
    let what = match config.pqn {
        Some(p) => format!("the PQN rollout of {} games × {} steps", p.games, p.rollout),
        None => format!("replay_capacity = {}", config.replay_capacity),
    };
    let lower = match config.pqn {
        Some(_) => "lower pqn.games or pqn.rollout".to_string(),
        None => format!(
            "lower replay_capacity (each transition takes {} bytes)",
            invaders::env::FRAME_LEN + 8
        ),
    };
    bail!(
        "{what} needs about {:.1} GiB of memory, but this process may use only {:.1} GiB ({which}): {lower}; nothing was written",
        gib(need),
        gib(have)
    )
}

/// The most bytes this process may still allocate, and what sets that: the lowest of the
/// memory the machine has available (`MemAvailable`), what the address-space limit leaves
/// (`ulimit -v`, less the process's size so far) and what its cgroup's limit leaves (v2's
/// `memory.max` less `memory.current`, v1's `memory.limit_in_bytes` less its usage). `None`
/// where none of them can be read.
pub(super) fn usable_bytes() -> Option<(u64, &'static str)> {
    let mut limits: Vec<(u64, &'static str)> = Vec::new();
    if let Some(b) = meminfo_kib("MemAvailable:") {
        limits.push((b * 1024, "the memory this machine has available"));
    }
    if let Some(b) = address_space_left() {
        limits.push((b, "what the address-space limit, ulimit -v, leaves"));
    }
    if let Some(b) = cgroup_left() {
        limits.push((b, "what this process's cgroup memory limit leaves"));
    }
    limits.into_iter().min_by_key(|l| l.0)
}

/// A `KEY: N kB` line of `/proc/meminfo`, in KiB.
fn meminfo_kib(key: &str) -> Option<u64> {
    kib_line(&std::fs::read_to_string("/proc/meminfo").ok()?, key)
}

/// The number of KiB on the line starting with `key` of `text`.
fn kib_line(text: &str, key: &str) -> Option<u64> {
    text.lines()
        .find(|l| l.starts_with(key))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// `RLIMIT_AS` less the process's virtual size (`VmSize`), if there is such a limit.
fn address_space_left() -> Option<u64> {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: `lim` is a valid rlimit for getrlimit to fill.
    if unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut lim) } != 0
        || lim.rlim_cur == libc::RLIM_INFINITY
    {
        return None;
    }
    let size = kib_line(
        &std::fs::read_to_string("/proc/self/status").ok()?,
        "VmSize:",
    )? * 1024;
    Some(lim.rlim_cur.saturating_sub(size))
}

/// What this process's cgroup memory limit leaves: v2's `memory.max` less `memory.current`
/// (of the process's own cgroup, else the root's), or v1's limit less its usage.
fn cgroup_left() -> Option<u64> {
    let read = |p: &str| -> Option<u64> { std::fs::read_to_string(p).ok()?.trim().parse().ok() };
    let own = std::fs::read_to_string("/proc/self/cgroup")
        .ok()
        .and_then(|t| {
            t.lines()
                .find_map(|l| l.strip_prefix("0::").map(|p| p.trim().to_string()))
        })
        .unwrap_or_default();
    for base in [format!("/sys/fs/cgroup{own}"), "/sys/fs/cgroup".to_string()] {
        let base = base.trim_end_matches('/');
        // "max" (no limit) does not parse: then there is none here.
        if let (Some(max), Some(cur)) = (
            read(&format!("{base}/memory.max")),
            read(&format!("{base}/memory.current")),
        ) {
            return Some(max.saturating_sub(cur));
        }
    }
    let v1 = "/sys/fs/cgroup/memory";
    match (
        read(&format!("{v1}/memory.limit_in_bytes")),
        read(&format!("{v1}/memory.usage_in_bytes")),
    ) {
        // v1 says "no limit" with a number near 2^63.
        (Some(max), Some(cur)) if max < 1 << 60 => Some(max.saturating_sub(cur)),
        _ => None,
    }
}
