//! markhold-config: the one error every site-file section reports, and the declarative
//! checks that produce it.
//!
//! A section validates itself as a list, one line per key; the first failing check is
//! the error:
//!
//! ```
//! use markhold_config::{above, open, open_closed, Checks};
//!
//! let (percentile, rate, floor) = (0.9, 0.5, 1.0);
//! Checks::new("exposure.aaec")
//!     .range("percentile", percentile, open(0.0, 1.0), "a fraction in (0, 1)")
//!     .range("learning_rate", rate, open_closed(0.0, 10.0), "a rate in (0, 10]")
//!     .positive("metric_floor_grey2", floor, "a positive value")
//!     .done()
//!     .unwrap();
//!
//! let e = Checks::new("camera")
//!     .range("exposure_max_us", 5.0, above(20.0), "microseconds, more than exposure_min_us")
//!     .done()
//!     .unwrap_err();
//! assert_eq!(
//!     e.to_string(),
//!     "camera.exposure_max_us = 5: expected microseconds, more than exposure_min_us"
//! );
//! ```
//!
//! Such lists are kept one check per line (`#[rustfmt::skip]` on the function): rustfmt
//! would spread each call over six lines and hide the table.
//!
//! Ranges are the standard ones (`a..=b` closed, `a..b` closed-open, `a..`, `..=b`) plus
//! [`open`], [`open_closed`], [`above`] and [`below`] for the bounds Rust has no syntax
//! for. NaN lies in no bounded range, so a float check written as a range rejects it.

use std::fmt;
use std::ops::{Bound, RangeBounds};
use std::path::{Path, PathBuf};

/// A site-file value the code cannot use: the dotted key, the value as written, what was
/// expected, and (filled in by the site loader) the file and line.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{}{key} = {value}: expected {expected}", place(.file, .line, .column))]
pub struct ConfigError {
    /// Dotted key, e.g. `exposure.aaec.learning_rate`.
    pub key: String,
    /// The offending value, printed.
    pub value: String,
    /// What is expected instead.
    pub expected: String,
    /// The site file, when the error came from one (boxed: the error stays small).
    pub file: Option<Box<Path>>,
    /// The 1-based line of the value (or of its table, when the file leaves it out).
    pub line: Option<usize>,
    /// The 1-based column (in characters) on `line` (32 bits keep the error small).
    pub column: Option<u32>,
}

fn place(file: &Option<Box<Path>>, line: &Option<usize>, column: &Option<u32>) -> String {
    match (file, line, column) {
        (Some(f), Some(l), Some(c)) => format!("{}:{l}:{c}: ", f.display()),
        (Some(f), Some(l), None) => format!("{}:{l}: ", f.display()),
        (Some(f), None, _) => format!("{}: ", f.display()),
        (None, _, _) => String::new(),
    }
}

impl ConfigError {
    pub fn new(
        key: impl Into<String>,
        value: impl fmt::Display,
        expected: impl Into<String>,
    ) -> Self {
        Self {
            key: key.into(),
            value: value.to_string(),
            expected: expected.into(),
            file: None,
            line: None,
            column: None,
        }
    }

    /// The same error located in `file` at `line`.
    pub fn at(mut self, file: impl Into<PathBuf>, line: usize) -> Self {
        self.file = Some(file.into().into_boxed_path());
        self.line = Some(line);
        self
    }

    /// The same error located in `file` at `line` and `column`.
    pub fn at_column(self, file: impl Into<PathBuf>, line: usize, column: usize) -> Self {
        let mut e = self.at(file, line);
        e.column = Some(u32::try_from(column).unwrap_or(u32::MAX));
        e
    }
}

/// `(lo, hi)`, both ends excluded.
pub fn open<T>(lo: T, hi: T) -> (Bound<T>, Bound<T>) {
    (Bound::Excluded(lo), Bound::Excluded(hi))
}

/// `(lo, hi]`.
pub fn open_closed<T>(lo: T, hi: T) -> (Bound<T>, Bound<T>) {
    (Bound::Excluded(lo), Bound::Included(hi))
}

/// `(lo, +inf)`; `+inf` itself is inside (see [`Checks::finite_range`]).
pub fn above<T>(lo: T) -> (Bound<T>, Bound<T>) {
    (Bound::Excluded(lo), Bound::Unbounded)
}

/// `(-inf, hi)`.
pub fn below<T>(hi: T) -> (Bound<T>, Bound<T>) {
    (Bound::Unbounded, Bound::Excluded(hi))
}

/// Shows a value through its `Debug` form, for arrays reported whole (`[0.2, 0.0, 0.0]`).
pub struct AsDebug<T>(pub T);

impl<T: fmt::Debug> fmt::Display for AsDebug<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}", self.0)
    }
}

/// The checks of one section (or sub-table), in order; the first failure is kept and the
/// checks after it are skipped.
#[must_use = "call .done() to get the result"]
pub struct Checks {
    prefix: String,
    first: Result<(), ConfigError>,
}

impl Checks {
    /// Checks of keys under `prefix` (dotted, e.g. `exposure.aaec`; empty for none).
    pub fn new(prefix: impl Into<String>) -> Self {
        Self {
            prefix: prefix.into(),
            first: Ok(()),
        }
    }

    /// The first failure, if any.
    pub fn done(self) -> Result<(), ConfigError> {
        self.first
    }

    /// `name`'s full dotted key.
    pub fn key(&self, name: &str) -> String {
        if self.prefix.is_empty() {
            name.to_string()
        } else if name.is_empty() {
            self.prefix.clone()
        } else {
            format!("{}.{name}", self.prefix)
        }
    }

    /// The general form: `ok` says whether `value` is acceptable (also for rules across
    /// keys, e.g. `max > min`).
    pub fn check(mut self, name: &str, value: impl fmt::Display, ok: bool, expected: &str) -> Self {
        if self.first.is_ok() && !ok {
            self.first = Err(ConfigError::new(self.key(name), value, expected));
        }
        self
    }

    /// Like [`Checks::check`], with the predicate applied to the value.
    pub fn satisfies<T: fmt::Display>(
        self,
        name: &str,
        value: T,
        ok: impl FnOnce(&T) -> bool,
        expected: &str,
    ) -> Self {
        let ok = self.first.is_err() || ok(&value);
        self.check(name, value, ok, expected)
    }

    /// `value` lies in `range`.
    pub fn range<T, R>(self, name: &str, value: T, range: R, expected: &str) -> Self
    where
        T: PartialOrd + fmt::Display,
        R: RangeBounds<T>,
    {
        let ok = range.contains(&value);
        self.check(name, value, ok, expected)
    }

    /// `value` is finite and lies in `range` (for ranges open toward infinity).
    pub fn finite_range<R: RangeBounds<f64>>(
        self,
        name: &str,
        value: f64,
        range: R,
        expected: &str,
    ) -> Self {
        let ok = value.is_finite() && range.contains(&value);
        self.check(name, value, ok, expected)
    }

    /// `value` is a finite number.
    pub fn finite(self, name: &str, value: f64, expected: &str) -> Self {
        self.check(name, value, value.is_finite(), expected)
    }

    /// `value` is finite and > 0.
    pub fn positive(self, name: &str, value: f64, expected: &str) -> Self {
        self.finite_range(name, value, above(0.0), expected)
    }

    /// `value` is finite and >= 0.
    pub fn non_negative(self, name: &str, value: f64, expected: &str) -> Self {
        self.finite_range(name, value, 0.0.., expected)
    }

    /// `value` is odd and lies in `range`.
    pub fn odd<R: RangeBounds<u32>>(
        self,
        name: &str,
        value: u32,
        range: R,
        expected: &str,
    ) -> Self {
        let ok = value % 2 == 1 && range.contains(&value);
        self.check(name, value, ok, expected)
    }

    /// `value` is one of `allowed`.
    pub fn one_of<T: PartialEq + fmt::Display>(
        self,
        name: &str,
        value: T,
        allowed: &[T],
        expected: &str,
    ) -> Self {
        let ok = allowed.contains(&value);
        self.check(name, value, ok, expected)
    }

    /// Every element of `values` lies in `range`; the first that does not is reported.
    pub fn each<R: RangeBounds<f64>>(
        self,
        name: &str,
        values: &[f64],
        range: R,
        expected: &str,
    ) -> Self {
        match values.iter().find(|v| !range.contains(v)) {
            Some(&bad) => self.check(name, bad, false, expected),
            None => self,
        }
    }

    /// Every element of `values` lies in `range`; the whole array is reported.
    pub fn all<R: RangeBounds<f64>>(
        self,
        name: &str,
        values: &[f64],
        range: R,
        expected: &str,
    ) -> Self {
        let ok = values.iter().all(|v| range.contains(v));
        self.check(name, AsDebug(values), ok, expected)
    }

    /// [`Checks::range`] of an optional key; a key left out passes.
    pub fn range_opt<T, R>(self, name: &str, value: Option<T>, range: R, expected: &str) -> Self
    where
        T: PartialOrd + fmt::Display,
        R: RangeBounds<T>,
    {
        match value {
            Some(v) => self.range(name, v, range, expected),
            None => self,
        }
    }

    /// Checks of an optional key, written as `|checks, value| checks...`; a key left out
    /// passes.
    pub fn opt<T>(self, value: Option<T>, f: impl FnOnce(Self, T) -> Self) -> Self {
        match value {
            Some(v) => f(self, v),
            None => self,
        }
    }

    /// Checks written elsewhere (a helper shared by several keys), in this list's order.
    pub fn with(self, f: impl FnOnce(Self) -> Self) -> Self {
        f(self)
    }

    /// Every element of `values` is finite; the first that is not is reported.
    pub fn each_finite(self, name: &str, values: &[f64], expected: &str) -> Self {
        match values.iter().find(|v| !v.is_finite()) {
            Some(&bad) => self.check(name, bad, false, expected),
            None => self,
        }
    }

    /// Runs the checks of a sub-table (or of anything that reports a [`ConfigError`])
    /// unless one already failed.
    pub fn then(mut self, sub: impl FnOnce() -> Result<(), ConfigError>) -> Self {
        if self.first.is_ok() {
            self.first = sub();
        }
        self
    }
}

/// Open a file that must be a regular file (not a device such as `/dev/zero`, a FIFO
/// that blocks until a writer comes, or a directory) no larger than `max_bytes`.
pub fn open_regular(path: &std::path::Path, max_bytes: u64) -> std::io::Result<std::fs::File> {
    use std::io::{Error, ErrorKind};
    // The type is checked before opening: opening a FIFO would wait for a writer.
    let meta = std::fs::metadata(path)?;
    if !meta.is_file() {
        return Err(Error::new(
            ErrorKind::InvalidInput,
            "not a regular file (a device, FIFO or directory)",
        ));
    }
    let file = std::fs::File::open(path)?;
    let len = file.metadata()?.len();
    if len > max_bytes {
        return Err(Error::new(
            ErrorKind::InvalidInput,
            format!("{len} bytes: larger than the {max_bytes} bytes accepted"),
        ));
    }
    Ok(file)
}

/// The text of a regular file of at most `max_bytes` ([`open_regular`]); a file that
/// grows while it is read is cut at the cap and refused.
pub fn read_regular(path: &std::path::Path, max_bytes: u64) -> std::io::Result<String> {
    use std::io::Read;
    let file = open_regular(path, max_bytes)?;
    let mut text = String::new();
    file.take(max_bytes.saturating_add(1))
        .read_to_string(&mut text)?;
    if text.len() as u64 > max_bytes {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("larger than the {max_bytes} bytes accepted"),
        ));
    }
    Ok(text)
}

/// The largest site or calibration file accepted, bytes.
pub const MAX_CONFIG_FILE_BYTES: u64 = 4 << 20;

/// Deserializes a fixed-size array of numbers, refusing a list of another length (serde's
/// own array reading takes the first N and drops the rest silently):
/// `#[serde(deserialize_with = "markhold_config::exact_array")]`.
pub fn exact_array<'de, D, const N: usize>(d: D) -> Result<[f64; N], D::Error>
where
    D: serde::Deserializer<'de>,
{
    use serde::de::Error as _;
    let v = <Vec<f64> as serde::Deserialize>::deserialize(d)?;
    let n = v.len();
    v.try_into()
        .map_err(|_| D::Error::custom(format!("{n} numbers: expected exactly {N}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err(c: Checks) -> ConfigError {
        c.done().expect_err("a bad value passed")
    }

    #[test]
    fn message_names_key_value_and_expected() {
        let e = err(Checks::new("station").positive("distance_m", -1.0, "a finite number > 0"));
        assert_eq!(
            e.to_string(),
            "station.distance_m = -1: expected a finite number > 0"
        );
        let e = e.at("/x/pool.toml", 41);
        assert_eq!(
            e.to_string(),
            "/x/pool.toml:41: station.distance_m = -1: expected a finite number > 0"
        );
        assert_eq!(Checks::new("").key("site.name"), "site.name");
    }

    #[test]
    fn ranges_reject_their_excluded_ends_and_nan() {
        let r = |v: f64, range: (Bound<f64>, Bound<f64>)| {
            Checks::new("s").range("k", v, range, "x").done().is_ok()
        };
        assert!(r(0.5, open(0.0, 1.0)));
        assert!(!r(0.0, open(0.0, 1.0)));
        assert!(!r(1.0, open(0.0, 1.0)));
        assert!(r(1.0, open_closed(0.0, 1.0)));
        assert!(!r(0.0, open_closed(0.0, 1.0)));
        assert!(!r(f64::NAN, open(0.0, 1.0)));
        assert!(!r(f64::NAN, above(0.0)));
        assert!(r(f64::INFINITY, above(0.0)));
        assert!(!r(1.0, below(1.0)));
        let c = |v: f64| Checks::new("s").range("k", v, 0.0..1.0, "x").done().is_ok();
        assert!(c(0.0) && !c(1.0) && !c(f64::NAN));
        let i = |v: u32| Checks::new("s").range("k", v, 1..=64, "x").done().is_ok();
        assert!(i(1) && i(64) && !i(0) && !i(65));
    }

    #[test]
    fn finite_and_sign_checks() {
        let ok = |c: Checks| c.done().is_ok();
        assert!(!ok(Checks::new("s").finite("k", f64::INFINITY, "x")));
        assert!(!ok(Checks::new("s").finite("k", f64::NAN, "x")));
        assert!(!ok(Checks::new("s").positive("k", 0.0, "x")));
        assert!(!ok(Checks::new("s").positive("k", f64::INFINITY, "x")));
        assert!(ok(Checks::new("s").non_negative("k", 0.0, "x")));
        assert!(!ok(Checks::new("s").non_negative("k", -0.1, "x")));
        assert!(!ok(Checks::new("s").finite_range(
            "k",
            f64::INFINITY,
            1.0..,
            "x"
        )));
    }

    #[test]
    fn odd_one_of_and_predicates() {
        let odd = |v: u32| Checks::new("s").odd("k", v, 1..=9, "x").done().is_ok();
        assert!(odd(1) && odd(9) && !odd(0) && !odd(4) && !odd(11));
        let e = err(Checks::new("s").one_of("k", 3, &[1, 2], "1 or 2"));
        assert_eq!(e.value, "3");
        let e = err(Checks::new("s").satisfies("k", 6, |v| v % 4 == 0, "a multiple of 4"));
        assert_eq!(e.expected, "a multiple of 4");
    }

    #[test]
    fn arrays_report_the_element_or_the_whole() {
        let e = err(Checks::new("v").each("m", &[1.0, -2.0, -3.0], 0.0.., "non-negative"));
        assert_eq!(e.value, "-2");
        let e = err(Checks::new("c").all("p", &[0.2, 3.0], -2.0..=2.0, "within 2 m"));
        assert_eq!(e.value, "[0.2, 3.0]");
    }

    #[test]
    fn optional_keys_pass_when_left_out() {
        assert!(Checks::new("s")
            .range_opt("k", None::<f64>, 0.0..=1.0, "x")
            .done()
            .is_ok());
        assert!(Checks::new("s")
            .range_opt("k", Some(2.0), 0.0..=1.0, "x")
            .done()
            .is_err());
        let e = err(Checks::new("s").opt(Some(-1.0), |c, v| c.positive("k", v, "x")));
        assert_eq!(e.key, "s.k");
        let e = err(Checks::new("s").with(|c| c.each_finite("k", &[0.0, f64::NAN], "x")));
        assert_eq!(e.value, "NaN");
    }

    #[test]
    fn first_failure_wins_and_later_checks_are_skipped() {
        let e = err(Checks::new("s")
            .range("a", 1, 0..=2, "fine")
            .range("b", 5, 0..=2, "first")
            .range("c", 9, 0..=2, "second")
            .then(|| Err(ConfigError::new("d", 0, "third"))));
        assert_eq!((e.key.as_str(), e.expected.as_str()), ("s.b", "first"));
        let e = err(Checks::new("s").then(|| Err(ConfigError::new("x.y", 0, "sub"))));
        assert_eq!(e.key, "x.y");
    }

    #[test]
    fn arrays_of_the_wrong_length_are_refused() {
        #[derive(serde::Deserialize, Debug)]
        struct T {
            #[serde(deserialize_with = "crate::exact_array")]
            v: [f64; 3],
        }
        let ok: Result<T, _> = serde_json_like("[1, 2, 3]");
        assert_eq!(ok.map(|t| t.v).ok(), Some([1.0, 2.0, 3.0]));
        for bad in ["[1, 2]", "[1, 2, 3, 4]"] {
            let e = serde_json_like::<T>(bad).expect_err(bad);
            assert!(e.contains("expected exactly 3"), "{bad}: {e}");
        }
    }

    /// `{"v": <list>}` through serde's value deserializer (no format crate here).
    fn serde_json_like<T: serde::de::DeserializeOwned>(list: &str) -> Result<T, String> {
        use serde::de::value::{Error, MapDeserializer, SeqDeserializer};
        let nums: Vec<f64> = list
            .trim_matches(['[', ']'])
            .split(',')
            .map(|x| x.trim().parse().map_err(|e| format!("{e}")))
            .collect::<Result<_, _>>()?;
        let seq = SeqDeserializer::<_, Error>::new(nums.into_iter());
        let map = MapDeserializer::<_, Error>::new(std::iter::once(("v", seq)));
        T::deserialize(map).map_err(|e| e.to_string())
    }
}
