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
}
