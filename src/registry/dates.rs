//! The registry's times: UTC, ISO 8601 with milliseconds
//! (`2026-11-22T23:05:00.123Z`), written and read here only.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// Now, UTC, ISO 8601 with milliseconds.
pub fn utc_now() -> String {
    format_utc(SystemTime::now())
}

/// `time` as UTC ISO 8601 with milliseconds (`2026-11-22T23:05:00.123Z`).
pub(crate) fn format_utc(time: SystemTime) -> String {
    let since = time.duration_since(UNIX_EPOCH).unwrap_or_default();
    let seconds = since.as_secs() as i64;
    let (days, rest) = (seconds.div_euclid(86_400), seconds.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{:03}Z",
        rest / 3600,
        rest / 60 % 60,
        rest % 60,
        since.subsec_millis()
    )
}

/// Parses the UTC times [`format_utc`] writes; `None` for anything else.
pub(crate) fn parse_utc(text: &str) -> Option<SystemTime> {
    let number = |range: std::ops::Range<usize>| -> Option<i64> { text.get(range)?.parse().ok() };
    let (year, month, day) = (number(0..4)?, number(5..7)?, number(8..10)?);
    let (hour, minute, second) = (number(11..13)?, number(14..16)?, number(17..19)?);
    let millis = number(20..23).unwrap_or(0);
    // Days from civil (H. Hinnant's algorithm), the inverse of the above.
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (month + 9) % 12;
    let doy = (153 * mp + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    let seconds = days * 86_400 + hour * 3600 + minute * 60 + second;
    let seconds = u64::try_from(seconds).ok()?;
    Some(UNIX_EPOCH + Duration::from_secs(seconds) + Duration::from_millis(millis as u64))
}

/// Seconds from `started` to `ended` (both as [`format_utc`] writes them).
pub(crate) fn seconds_between(started: &str, ended: &str) -> Option<f64> {
    let (a, b) = (parse_utc(started)?, parse_utc(ended)?);
    Some(b.duration_since(a).ok()?.as_secs_f64())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_utc_dates() {
        let t = UNIX_EPOCH + Duration::from_millis(1_700_000_000_123);
        assert_eq!(format_utc(t), "2023-11-14T22:13:20.123Z");
        assert_eq!(format_utc(UNIX_EPOCH), "1970-01-01T00:00:00.000Z");
        let leap = UNIX_EPOCH + Duration::from_secs(951_782_400); // 2000-02-29
        assert_eq!(format_utc(leap), "2000-02-29T00:00:00.000Z");
    }

    #[test]
    fn parses_what_format_utc_writes() {
        let t = UNIX_EPOCH + Duration::from_millis(1_763_852_700_456);
        assert_eq!(parse_utc(&format_utc(t)), Some(t));
        assert_eq!(parse_utc("yesterday"), None);
        assert_eq!(
            seconds_between("2026-11-22T23:05:00.123Z", "2026-11-22T23:06:01.623Z"),
            Some(61.5)
        );
    }
}
