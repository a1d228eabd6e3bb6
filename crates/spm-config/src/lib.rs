//! Loading TOML configuration files with diagnostics a person can act on: every error names
//! the file, the 1-based line (and column where the parser gives one) and the dotted path of
//! the field, e.g. `sim-hopg.toml:42: field `scanner.nonlinearity_x.cubic` must be finite`.
//!
//! This is the one config-diagnostics module of the workspace: the simulator's config, the
//! calibration plan and the job file all load through it.
//!
//! - Parse errors come from the toml crate with its own byte span; [`TomlLocator`] turns the
//!   span into a field path by walking the document as toml's own parser (`toml_edit`) read
//!   it, with the span of every key and value: tables, dotted keys, inline tables, arrays and
//!   arrays of tables (`steps[2].width_nm`) are located exactly, without re-scanning text.
//! - Semantic errors ([`ValidationError`]: a field path and a reason) are located the other
//!   way: the path is looked up in the document and its key's line reported.
//!
//! ```
//! #[derive(serde::Deserialize, Debug)]
//! #[serde(deny_unknown_fields)]
//! struct Scanner { gain_nm_per_v: f64 }
//! #[derive(serde::Deserialize, Debug)]
//! #[serde(deny_unknown_fields)]
//! struct Config { scanner: Scanner }
//!
//! let text = "[scanner]\ngain_nm_per_v = 2.0\ngian = 1\n";
//! let err = spm_config::parse_toml::<Config>(text, "scanner.toml").unwrap_err();
//! assert_eq!(err.field(), Some("scanner.gian"));
//! assert_eq!(err.line(), Some(3));
//! assert!(err.to_string().starts_with("scanner.toml:3:1: field `scanner.gian`: unknown field"));
//! ```
#![doc = include_str!("../README.md")]

mod locate;

pub use locate::{TomlLocator, line_column};

use serde::de::DeserializeOwned;
use std::path::{Path, PathBuf};

/// Why a configuration could not be loaded.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read config `{}`: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The file is not a config file: not a regular file, or larger than the limit.
    #[error("`{}`: {reason}", path.display())]
    NotAConfigFile {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The TOML is malformed, has an unknown or missing field or a value of the wrong type.
    #[error("{source_name}{}: {}{message}", line_suffix(*line, *column), field_prefix(field.as_deref()))]
    Parse {
        /// File name or other label of the text.
        source_name: String,
        /// 1-based line, when known.
        line: Option<usize>,
        /// 1-based column, when known.
        column: Option<usize>,
        /// Dotted path of the offending field, when known.
        field: Option<String>,
        /// The parser's message.
        message: String,
    },
    /// A value is well-formed but invalid.
    #[error("{source_name}{}: field `{field}` {reason}", line_suffix(*line, None))]
    Invalid {
        /// File name or other label of the text.
        source_name: String,
        /// 1-based line of the field, when it can be found.
        line: Option<usize>,
        /// Dotted path of the field, e.g. `scanner.nonlinearity_x.cubic`.
        field: String,
        /// What is wrong.
        reason: String,
    },
}

fn line_suffix(line: Option<usize>, column: Option<usize>) -> String {
    match (line, column) {
        (Some(l), Some(c)) => format!(":{l}:{c}"),
        (Some(l), None) => format!(":{l}"),
        _ => String::new(),
    }
}

fn field_prefix(field: Option<&str>) -> String {
    field.map(|f| format!("field `{f}`: ")).unwrap_or_default()
}

impl ConfigError {
    /// Dotted path of the offending field, when known.
    #[must_use]
    pub fn field(&self) -> Option<&str> {
        match self {
            Self::Io { .. } | Self::NotAConfigFile { .. } => None,
            Self::Parse { field, .. } => field.as_deref(),
            Self::Invalid { field, .. } => Some(field),
        }
    }
    /// 1-based line of the problem, when known.
    #[must_use]
    pub fn line(&self) -> Option<usize> {
        match self {
            Self::Io { .. } | Self::NotAConfigFile { .. } => None,
            Self::Parse { line, .. } | Self::Invalid { line, .. } => *line,
        }
    }

    /// A semantic failure located in `text`: the line of the field, if it is written there.
    #[must_use]
    pub fn invalid(text: &str, source_name: &str, problem: ValidationError) -> Self {
        Self::Invalid {
            source_name: source_name.to_owned(),
            line: TomlLocator::new(text).line_of(&problem.field),
            field: problem.field,
            reason: problem.reason,
        }
    }
}

/// A semantic validation failure, before it is located in a file.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("field `{field}` {reason}")]
pub struct ValidationError {
    /// Dotted path of the field (`a.b[2].c`).
    pub field: String,
    /// What is wrong, as a predicate: "must be finite, got NaN".
    pub reason: String,
}

impl ValidationError {
    /// A failure of `field`.
    pub fn new(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self {
            field: field.into(),
            reason: reason.into(),
        }
    }
}

/// The one range checker of the configs (spm-sim's simulator, spm-calibration's plan): each
/// check names its field with the checker's prefix (`"plan."`, `"backend.sim."`), and every
/// number must be finite before its range is looked at (a NaN passes no comparison, so it
/// would pass a range written as two negated comparisons).
#[derive(Clone, Copy, Debug)]
pub struct RangeChecker<'a> {
    prefix: &'a str,
}

impl<'a> RangeChecker<'a> {
    /// A checker naming fields `prefix` + field.
    pub fn new(prefix: &'a str) -> Self {
        Self { prefix }
    }

    /// The failure of `field` with `reason`.
    ///
    /// # Errors
    /// Always: [`ValidationError`] naming the prefixed field.
    pub fn fail(&self, field: &str, reason: impl Into<String>) -> Result<(), ValidationError> {
        Err(ValidationError::new(
            format!("{}{field}", self.prefix),
            reason,
        ))
    }

    /// `value` is a finite number.
    ///
    /// # Errors
    /// [`ValidationError`] naming the field.
    pub fn finite(&self, field: &str, value: f64) -> Result<(), ValidationError> {
        if value.is_finite() {
            Ok(())
        } else {
            self.fail(field, format!("must be a finite number, got {value}"))
        }
    }

    /// `value` is finite and > 0.
    ///
    /// # Errors
    /// [`ValidationError`] naming the field.
    pub fn positive(&self, field: &str, value: f64) -> Result<(), ValidationError> {
        self.finite(field, value)?;
        if value > 0.0 {
            Ok(())
        } else {
            self.fail(field, format!("must be > 0, got {value}"))
        }
    }

    /// `value` is finite and in `[min, max]`.
    ///
    /// # Errors
    /// [`ValidationError`] naming the field.
    pub fn range(
        &self,
        field: &str,
        value: f64,
        min: f64,
        max: f64,
    ) -> Result<(), ValidationError> {
        self.finite(field, value)?;
        if (min..=max).contains(&value) {
            Ok(())
        } else {
            self.fail(
                field,
                format!("must be a finite number in [{min}, {max}], got {value}"),
            )
        }
    }

    /// `value` is finite, > 0 and in `[min, max]`.
    ///
    /// # Errors
    /// [`ValidationError`] naming the field.
    pub fn range_positive(
        &self,
        field: &str,
        value: f64,
        min: f64,
        max: f64,
    ) -> Result<(), ValidationError> {
        self.positive(field, value)?;
        self.range(field, value, min, max)
    }

    /// An integer `value` in `[min, max]`.
    ///
    /// # Errors
    /// [`ValidationError`] naming the field.
    pub fn count<T: PartialOrd + std::fmt::Display>(
        &self,
        field: &str,
        value: T,
        min: T,
        max: T,
    ) -> Result<(), ValidationError> {
        if min <= value && value <= max {
            Ok(())
        } else {
            self.fail(field, format!("must be in [{min}, {max}], got {value}"))
        }
    }

    /// An integer `value` ≤ `max`.
    ///
    /// # Errors
    /// [`ValidationError`] naming the field.
    pub fn at_most(&self, field: &str, value: u32, max: u32) -> Result<(), ValidationError> {
        if value <= max {
            Ok(())
        } else {
            self.fail(field, format!("must be ≤ {max}, got {value}"))
        }
    }

    /// An integer `value` ≥ 1.
    ///
    /// # Errors
    /// [`ValidationError`] naming the field.
    pub fn at_least_one(&self, field: &str, value: u32) -> Result<(), ValidationError> {
        if value >= 1 {
            Ok(())
        } else {
            self.fail(field, "must be at least 1")
        }
    }
}

/// A configuration that checks its own values after parsing.
pub trait Validate {
    /// Checks every value.
    ///
    /// # Errors
    /// The first invalid field.
    fn validate(&self) -> Result<(), ValidationError>;
}

/// Parses a TOML text into `T`; `source_name` (a file name) labels errors.
///
/// # Errors
/// [`ConfigError::Parse`] naming the line, column and field.
pub fn parse_toml<T: DeserializeOwned>(text: &str, source_name: &str) -> Result<T, ConfigError> {
    toml::from_str(text).map_err(|e| parse_error(text, source_name, &e))
}

/// Parses and validates a TOML text.
///
/// # Errors
/// [`ConfigError::Parse`] or [`ConfigError::Invalid`] naming the line and field.
pub fn parse_and_validate<T: DeserializeOwned + Validate>(
    text: &str,
    source_name: &str,
) -> Result<T, ConfigError> {
    let value: T = parse_toml(text, source_name)?;
    value
        .validate()
        .map_err(|v| ConfigError::invalid(text, source_name, v))?;
    Ok(value)
}

/// Largest config file read, bytes: configs are small hand-written files; anything larger is
/// a mistake (a data file given as a config, say).
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// Reads a config file: a regular file of at most [`MAX_CONFIG_BYTES`], UTF-8.
///
/// # Errors
/// [`ConfigError::Io`] or [`ConfigError::NotAConfigFile`] naming the file.
pub fn read_config_file(path: &Path) -> Result<String, ConfigError> {
    let io = |source| ConfigError::Io {
        path: path.to_path_buf(),
        source,
    };
    let meta = std::fs::metadata(path).map_err(io)?;
    if !meta.is_file() {
        return Err(ConfigError::NotAConfigFile {
            path: path.to_path_buf(),
            reason: "not a regular file (a config must be a TOML file)".into(),
        });
    }
    if meta.len() > MAX_CONFIG_BYTES {
        return Err(ConfigError::NotAConfigFile {
            path: path.to_path_buf(),
            reason: format!(
                "{} bytes is larger than a config file can be ({MAX_CONFIG_BYTES} bytes)",
                meta.len()
            ),
        });
    }
    std::fs::read_to_string(path).map_err(io)
}

/// Reads, parses and validates a config file.
///
/// # Errors
/// As [`read_config_file`] and [`parse_and_validate`].
pub fn load_file<T: DeserializeOwned + Validate>(path: &Path) -> Result<T, ConfigError> {
    let text = read_config_file(path)?;
    parse_and_validate(&text, &path.display().to_string())
}

/// A toml parse error as a [`ConfigError::Parse`] with its line, column and field path.
#[must_use]
pub fn parse_error(text: &str, source_name: &str, e: &toml::de::Error) -> ConfigError {
    let message = e.message().trim().to_owned();
    let locator = TomlLocator::new(text);
    let (mut line, mut column, field) = match e.span() {
        Some(span) => {
            let (l, c) = line_column(text, span.start);
            (Some(l), Some(c), locator.field_for_error(span, &message))
        }
        None => (None, None, quoted_name(&message)),
    };
    // Some errors span a whole table (an internally tagged enum reports its unknown fields
    // at the table): when the named field is written, point at it.
    if let Some(exact) = field.as_deref().and_then(|f| locator.exact_line_of(f))
        && line.is_none_or(|l| exact > l)
    {
        line = Some(exact);
        column = None;
    }
    ConfigError::Parse {
        source_name: source_name.to_owned(),
        line,
        column,
        field,
        message,
    }
}

/// The name inside the first pair of backticks of a serde message ("unknown field `x`",
/// "missing field `x`").
fn quoted_name(message: &str) -> Option<String> {
    let start = message.find('`')? + 1;
    let len = message.get(start..)?.find('`')?;
    message.get(start..start + len).map(str::to_owned)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The field path and line a locator gives for the byte offset of `marker` in `text`
    /// (the first occurrence), and the line it gives back for that path.
    fn check(text: &str, marker: &str, expected_path: &str, expected_line: usize) {
        let locator = TomlLocator::new(text);
        let offset = text.find(marker).expect("marker in text");
        assert_eq!(
            locator.field_at(offset).as_deref(),
            Some(expected_path),
            "field at {marker:?}"
        );
        assert_eq!(
            locator.line_of(expected_path),
            Some(expected_line),
            "line of {expected_path}"
        );
    }

    const DOC: &str = "\
top = 1
[scanner]
gain = 2.0 # comment with = sign
nonlinearity_x = { quadratic = 0.1, cubic = nan }
dotted.inner = 3

[[surface.steps]]
height_nm = 0.3354

[[surface.steps]]
height_nm = 0.67
widths = [1.0, { w = 2 }]
";

    #[test]
    fn fields_are_located_in_every_kind_of_table() {
        check(DOC, "top", "top", 1);
        check(DOC, "gain", "scanner.gain", 3);
        check(DOC, "2.0", "scanner.gain", 3);
        check(DOC, "cubic", "scanner.nonlinearity_x.cubic", 4);
        check(DOC, "nan", "scanner.nonlinearity_x.cubic", 4);
        check(DOC, "inner", "scanner.dotted.inner", 5);
        check(DOC, "0.67", "surface.steps[1].height_nm", 11);
        check(DOC, "w = 2", "surface.steps[1].widths[1].w", 12);
    }

    #[test]
    fn unwritten_fields_fall_back_to_their_table() {
        let locator = TomlLocator::new(DOC);
        assert_eq!(locator.line_of("scanner.missing"), Some(2));
        assert_eq!(locator.line_of("surface.steps[0].missing"), Some(7));
        assert_eq!(locator.line_of("nowhere.at.all"), None);
        assert_eq!(locator.line_of("a..b[x]"), None);
    }

    #[test]
    fn line_and_column_are_one_based_and_char_safe() {
        assert_eq!(line_column("a\nbc", 0), (1, 1));
        assert_eq!(line_column("a\nbc", 3), (2, 2));
        assert_eq!(line_column("µm\nx", 1), (1, 1));
        assert_eq!(line_column("x", 99), (1, 2));
    }

    #[derive(serde::Deserialize, Debug)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Inner {
        quadratic: f64,
        cubic: f64,
    }
    #[derive(serde::Deserialize, Debug)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Scanner {
        gain: f64,
        nonlinearity_x: Inner,
    }
    #[derive(serde::Deserialize, Debug)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Doc {
        scanner: Scanner,
    }
    impl Validate for Doc {
        fn validate(&self) -> Result<(), ValidationError> {
            if self.scanner.nonlinearity_x.cubic.is_finite() {
                Ok(())
            } else {
                Err(ValidationError::new(
                    "scanner.nonlinearity_x.cubic",
                    "must be finite",
                ))
            }
        }
    }

    fn check_error(text: &str, field: Option<&str>, line: Option<usize>) {
        let err = parse_and_validate::<Doc>(text, "f.toml").expect_err("an invalid config");
        assert_eq!(err.field(), field, "{err}");
        assert_eq!(err.line(), line, "{err}");
        assert!(err.to_string().starts_with("f.toml"), "{err}");
    }

    #[test]
    fn parse_and_validation_errors_name_field_and_line() {
        let ok = "[scanner]\ngain = 1.0\nnonlinearity_x = { quadratic = 0.0, cubic = 0.0 }\n";
        assert!(parse_and_validate::<Doc>(ok, "f.toml").is_ok());
        // A value of the wrong type inside an inline table.
        check_error(
            "[scanner]\ngain = 1.0\nnonlinearity_x = { quadratic = \"x\", cubic = 0.0 }\n",
            Some("scanner.nonlinearity_x.quadratic"),
            Some(3),
        );
        // An unknown field inside an inline table.
        check_error(
            "[scanner]\ngain = 1.0\nnonlinearity_x = { quadratic = 0.0, cubic = 0.0, quartic = 1 }\n",
            Some("scanner.nonlinearity_x.quartic"),
            Some(3),
        );
        // A missing field: the table is named, with the field.
        check_error(
            "[scanner]\nnonlinearity_x = { quadratic = 0.0, cubic = 0.0 }\n",
            Some("scanner.gain"),
            Some(1),
        );
        // A semantic error located through the document.
        check_error(
            "[scanner]\ngain = 1.0\n\nnonlinearity_x = { quadratic = 0.0, cubic = nan }\n",
            Some("scanner.nonlinearity_x.cubic"),
            Some(4),
        );
        // Malformed TOML: a line, no field.
        let err = parse_and_validate::<Doc>("[scanner\n", "f.toml").expect_err("malformed");
        assert_eq!(err.line(), Some(1), "{err}");
    }
}

#[cfg(test)]
mod range_checker_tests {
    use super::RangeChecker;

    /// `check(result, expected)`: `None` = accepted, `Some((field, reason))` = refused.
    fn check(result: Result<(), super::ValidationError>, expected: Option<(&str, &str)>) {
        match (result, expected) {
            (Ok(()), None) => {}
            (Err(e), Some((field, reason))) => {
                assert_eq!((e.field.as_str(), e.reason.as_str()), (field, reason));
            }
            (got, want) => panic!("got {got:?}, expected {want:?}"),
        }
    }

    #[test]
    fn each_check_names_the_prefixed_field_and_refuses_what_is_outside() {
        let v = RangeChecker::new("plan.");
        check(v.range("a", 1.0, 0.0, 2.0), None);
        check(v.range("a", 2.0, 0.0, 2.0), None);
        check(
            v.range("a", 2.5, 0.0, 2.0),
            Some(("plan.a", "must be a finite number in [0, 2], got 2.5")),
        );
        check(
            v.range("a", f64::NAN, 0.0, 2.0),
            Some(("plan.a", "must be a finite number, got NaN")),
        );
        check(
            v.range_positive("b", 0.0, 0.0, 2.0),
            Some(("plan.b", "must be > 0, got 0")),
        );
        check(v.range_positive("b", 1e-3, 1e-4, 2.0), None);
        check(
            v.positive("c", f64::INFINITY),
            Some(("plan.c", "must be a finite number, got inf")),
        );
        check(v.count("d", 3u32, 1, 3), None);
        check(
            v.count("d", -5i64, -4, 4),
            Some(("plan.d", "must be in [-4, 4], got -5")),
        );
        check(v.at_most("e", 9, 8), Some(("plan.e", "must be ≤ 8, got 9")));
        check(
            v.at_least_one("f", 0),
            Some(("plan.f", "must be at least 1")),
        );
        check(v.at_least_one("f", 1), None);
        check(v.fail("g", "why"), Some(("plan.g", "why")));
    }
}
