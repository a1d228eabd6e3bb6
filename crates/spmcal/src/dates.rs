//! Parsing the command line's dates: RFC 3339 date-times or plain `YYYY-MM-DD` (UTC midnight).

use crate::error::CliError;

/// UTC seconds since the Unix epoch of `text`, naming `flag` on failure.
pub fn parse_utc(flag: &str, text: &str) -> Result<f64, CliError> {
    use time::format_description::well_known::Rfc3339;
    if let Ok(t) = time::OffsetDateTime::parse(text, &Rfc3339) {
        return Ok(t.unix_timestamp() as f64 + f64::from(t.nanosecond()) * 1e-9);
    }
    let format = time::macros::format_description!("[year]-[month]-[day]");
    match time::Date::parse(text, &format) {
        Ok(date) => Ok(date.midnight().assume_utc().unix_timestamp() as f64),
        Err(_) => Err(CliError::BadInput(format!(
            "{flag} {text:?}: expected an RFC 3339 date-time (2026-11-21T10:00:00Z) or a date (2026-11-21)"
        ))),
    }
}

/// Like [`parse_utc`] for `--until`: a plain date means the whole day (up to its last
/// instant), so `--since D --until D` selects the records of day D.
pub fn parse_utc_until(flag: &str, text: &str) -> Result<f64, CliError> {
    use time::format_description::well_known::Rfc3339;
    if time::OffsetDateTime::parse(text, &Rfc3339).is_ok() {
        return parse_utc(flag, text);
    }
    // One microsecond before the next midnight: CDB times are stored in seconds as f64
    // (µs resolution for present dates).
    parse_utc(flag, text).map(|midnight| midnight + 86_400.0 - 1e-6)
}

/// Parses `--since` and `--until` and checks that the window is not reversed.
pub fn parse_window(
    since: Option<&str>,
    until: Option<&str>,
) -> Result<(Option<f64>, Option<f64>), CliError> {
    let since_s = since.map(|s| parse_utc("--since", s)).transpose()?;
    let until_s = until.map(|s| parse_utc_until("--until", s)).transpose()?;
    if let (Some(a), Some(b), Some(a_text), Some(b_text)) = (since_s, until_s, since, until)
        && a > b
    {
        return Err(CliError::BadInput(format!(
            "--since {a_text} is after --until {b_text}: the window is reversed"
        )));
    }
    Ok((since_s, until_s))
}

#[cfg(test)]
mod tests {
    use super::parse_utc;

    fn check(text: &str, expected: Option<f64>) {
        assert_eq!(parse_utc("--since", text).ok(), expected, "{text}");
    }

    #[test]
    fn dates_and_date_times_parse_to_unix_seconds() {
        check("1970-01-02", Some(86400.0));
        check("1970-01-01T00:01:00Z", Some(60.0));
        check("1970-01-01T01:00:00+01:00", Some(0.0));
        check("yesterday", None);
        check("2026-13-01", None);
    }

    #[test]
    fn a_plain_until_date_covers_the_whole_day_and_reversed_windows_are_refused() {
        let (a, b) =
            super::parse_window(Some("1970-01-02"), Some("1970-01-02")).unwrap_or_default();
        assert_eq!(a, Some(86400.0));
        assert!(b.is_some_and(|b| b > 2.0 * 86400.0 - 1e-3 && b < 2.0 * 86400.0));
        assert!(super::parse_window(Some("1970-01-03"), Some("1970-01-02")).is_err());
    }
}
