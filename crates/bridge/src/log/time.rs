//! Wall-clock time for the log epoch and file names, without a date crate.

use std::time::{SystemTime, UNIX_EPOCH};

/// Nanoseconds since the Unix epoch (0 if the clock is before 1970).
pub fn now_unix_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

/// CPU time of the calling thread, ns (Linux: `/proc/thread-self/schedstat`; `None`
/// elsewhere): what the writer thread reports as its cost.
pub fn thread_cpu_ns() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    text.split_whitespace().next()?.parse().ok()
}

/// Civil date (year, month, day) from days since 1970-01-01 (Howard Hinnant's algorithm).
fn civil_from_days(days: i64) -> (i64, u32, u32) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let y = yoe + era * 400;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    (if m <= 2 { y + 1 } else { y }, m, d)
}

fn parts(unix_ns: u64) -> (i64, u32, u32, u64, u64, u64, u64) {
    let secs = unix_ns / 1_000_000_000;
    let (y, mo, d) = civil_from_days((secs / 86_400) as i64);
    let sod = secs % 86_400;
    (y, mo, d, sod / 3600, sod / 60 % 60, sod % 60, unix_ns % 1_000_000_000 / 1_000_000)
}

/// `20260314T101500Z`: for file names.
pub fn format_utc_basic(unix_ns: u64) -> String {
    let (y, mo, d, h, mi, s, _) = parts(unix_ns);
    format!("{y:04}{mo:02}{d:02}T{h:02}{mi:02}{s:02}Z")
}

/// `2026-03-14T10:15:00.123Z`: for humans and metadata.
pub fn format_utc_iso(unix_ns: u64) -> String {
    let (y, mo, d, h, mi, s, ms) = parts(unix_ns);
    format!("{y:04}-{mo:02}-{d:02}T{h:02}:{mi:02}:{s:02}.{ms:03}Z")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_formatting_matches_known_dates() {
        assert_eq!(format_utc_basic(0), "19700101T000000Z");
        // 2000-02-29 12:34:56.789 UTC = 951827696.789 s.
        assert_eq!(format_utc_iso(951_827_696_789_000_000), "2000-02-29T12:34:56.789Z");
        // 2024-12-31 23:59:59 UTC = 1735689599 s.
        assert_eq!(format_utc_basic(1_735_689_599_000_000_000), "20241231T235959Z");
    }
}
