//! The memory a run may hold (docs/theory.md §12 "Memory"). Every array whose size grows faster
//! than the chain itself (the centralized filter's `(N n)²`, the joint filter's bands `N (k+1) n²`
//! and `A_eff`'s band, a smoother's stored steps) is checked against `max_memory` before it is
//! allocated, so that a size nobody can hold is refused with the figure and the limit instead of
//! aborting the process or waking the out-of-memory killer.

use crate::error::{Error, Result};

/// Default `max_memory`: 8 GiB.
pub const DEFAULT_MAX_MEMORY: u64 = 8 << 30;

/// Refuses `need` bytes (a real number, so that no product of sizes overflows) above `limit`;
/// `what` names what needs them.
pub fn check(need: f64, limit: u64, what: impl FnOnce() -> String) -> Result<()> {
    if need > limit as f64 {
        return Err(Error::OverMemory {
            what: what(),
            need: need.min(u64::MAX as f64) as u64,
            limit,
        });
    }
    Ok(())
}

/// Parses `--max-memory`: bytes, or a number with a `K`, `M` or `G` suffix (powers of 1024).
pub fn parse_bytes(text: &str) -> std::result::Result<u64, String> {
    let t = text.trim();
    let (digits, scale) = match t.chars().last() {
        Some('K' | 'k') => (&t[..t.len() - 1], 1u64 << 10),
        Some('M' | 'm') => (&t[..t.len() - 1], 1 << 20),
        Some('G' | 'g') => (&t[..t.len() - 1], 1 << 30),
        _ => (t, 1),
    };
    let value: f64 = digits
        .trim()
        .parse()
        .map_err(|_| format!("`{text}`: expected bytes, or a number with a K, M or G suffix"))?;
    if !value.is_finite() || value < 0.0 {
        return Err(format!("`{text}`: expected a non-negative size"));
    }
    Ok((value * scale as f64) as u64)
}

/// A size in bytes for messages (e.g. `1.5 GiB`).
pub fn human_bytes(bytes: u64) -> String {
    let b = bytes as f64;
    if b >= (1u64 << 30) as f64 {
        format!("{:.1} GiB", b / (1u64 << 30) as f64)
    } else if b >= (1u64 << 20) as f64 {
        format!("{:.1} MiB", b / (1u64 << 20) as f64)
    } else if b >= 1024.0 {
        format!("{:.1} KiB", b / 1024.0)
    } else {
        format!("{bytes} B")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_suffixes() {
        assert_eq!(parse_bytes("1024"), Ok(1024));
        assert_eq!(parse_bytes("2K"), Ok(2048));
        assert_eq!(parse_bytes("1.5M"), Ok(3 << 19));
        assert_eq!(parse_bytes("8G"), Ok(8 << 30));
        assert!(parse_bytes("lots").is_err());
        assert!(parse_bytes("-1").is_err());
        assert_eq!(human_bytes(3 << 29), "1.5 GiB");
    }
}
