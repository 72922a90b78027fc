//! When a survey was acquired: a span of time, since a date names a whole day, a month a whole
//! month, and campaigns run for weeks ("2000-02-11/2000-02-22").
//!
//! Only the epoch decides which of two surveys saw the ground last (see
//! [`crate::evidence::PairEvidence::changes`]); the time a file arrived never does, since that
//! would make the store depend on the order of its files.

use chrono::{DateTime, NaiveDate, NaiveDateTime, NaiveTime};
use std::fmt;

/// A span of time, Unix seconds (UTC), `start` included and `end` not.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Epoch {
    /// Its first second.
    pub start: i64,
    /// The second after its last.
    pub end: i64,
}

/// Why a text is no epoch.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{text:?} is not an ISO 8601 date, date-time or interval of them ({why})")]
pub struct EpochError {
    text: String,
    why: &'static str,
}

impl Epoch {
    /// Parses ISO 8601 as producers write acquisition dates: a year (`2011`), a month
    /// (`2011-02`), a day (`2011-02-11`), a date-time with or without an offset
    /// (`2011-02-11T10:30:00Z`; without one it is taken as UTC), an interval of any two of
    /// those (`2000-02-11/2000-02-22`, the span from the start of the first to the end of the
    /// second), and TIFF's `DateTime` (`2011:02:11 10:30:00`).
    pub fn parse(text: &str) -> Result<Epoch, EpochError> {
        let fail = |why| EpochError {
            text: text.to_string(),
            why,
        };
        let t = text.trim();
        if let Some((a, b)) = t.split_once('/') {
            let (a, b) = (one(a.trim()), one(b.trim()));
            let (Some(a), Some(b)) = (a, b) else {
                return Err(fail("an end of the interval is no date"));
            };
            if b.end <= a.start {
                return Err(fail("the interval ends before it starts"));
            }
            return Ok(Epoch {
                start: a.start,
                end: b.end,
            });
        }
        one(t).ok_or_else(|| fail("no date"))
    }

    /// Whether all of this span comes after all of `other`: only then did this survey see
    /// the ground later. Spans that overlap give neither precedence.
    pub fn after(&self, other: &Epoch) -> bool {
        self.start >= other.end
    }

    /// Whether the span holds any time on or before `t` (Unix seconds).
    pub fn begun_by(&self, t: i64) -> bool {
        self.start <= t
    }
}

impl fmt::Display for Epoch {
    /// As ISO 8601: the first day, or the interval of the first and last days; with times
    /// where a bound is not midnight.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let at = |s: i64| DateTime::from_timestamp(s, 0).map(|d| d.naive_utc());
        let (Some(a), Some(b)) = (at(self.start), at(self.end - 1)) else {
            return write!(f, "{}/{}", self.start, self.end);
        };
        let whole_days = self.start % 86_400 == 0 && self.end % 86_400 == 0;
        if whole_days {
            if a.date() == b.date() {
                write!(f, "{}", a.date())
            } else {
                write!(f, "{}/{}", a.date(), b.date())
            }
        } else {
            let b = at(self.end).unwrap_or(b);
            write!(f, "{}Z/{}Z", a.format("%FT%T"), b.format("%FT%T"))
        }
    }
}

/// One date or date-time, as the span it names.
fn one(t: &str) -> Option<Epoch> {
    let day = |d: NaiveDate| d.and_time(NaiveTime::MIN).and_utc().timestamp();
    // A year, a month, a day.
    if t.len() == 4 && t.bytes().all(|b| b.is_ascii_digit()) {
        let y: i32 = t.parse().ok()?;
        return Some(Epoch {
            start: day(NaiveDate::from_ymd_opt(y, 1, 1)?),
            end: day(NaiveDate::from_ymd_opt(y + 1, 1, 1)?),
        });
    }
    if t.len() == 7 {
        let d = NaiveDate::parse_from_str(&format!("{t}-01"), "%Y-%m-%d").ok()?;
        let next = d.checked_add_months(chrono::Months::new(1))?;
        return Some(Epoch {
            start: day(d),
            end: day(next),
        });
    }
    if let Ok(d) = NaiveDate::parse_from_str(t, "%Y-%m-%d") {
        return Some(Epoch {
            start: day(d),
            end: day(d.succ_opt()?),
        });
    }
    // An instant, to the second it names.
    let instant = DateTime::parse_from_rfc3339(t)
        .map(|d| d.timestamp())
        .ok()
        .or_else(|| {
            [
                "%Y-%m-%dT%H:%M:%S%.f",
                "%Y-%m-%dT%H:%M",
                "%Y:%m:%d %H:%M:%S",
            ]
            .iter()
            .find_map(|f| NaiveDateTime::parse_from_str(t, f).ok())
            .map(|d| d.and_utc().timestamp())
        })?;
    Some(Epoch {
        start: instant,
        end: instant + 1,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_forms_producers_write_parse_to_their_spans() {
        let e = |s| Epoch::parse(s).unwrap();
        let d = |s| {
            NaiveDate::parse_from_str(s, "%Y-%m-%d")
                .unwrap()
                .and_time(NaiveTime::MIN)
                .and_utc()
                .timestamp()
        };
        assert_eq!(
            e("2011"),
            Epoch {
                start: d("2011-01-01"),
                end: d("2012-01-01")
            }
        );
        assert_eq!(
            e("2012-02"),
            Epoch {
                start: d("2012-02-01"),
                end: d("2012-03-01")
            }
        );
        assert_eq!(
            e("2000-02-11"),
            Epoch {
                start: d("2000-02-11"),
                end: d("2000-02-12")
            }
        );
        assert_eq!(
            e("2000-02-11/2000-02-22"),
            Epoch {
                start: d("2000-02-11"),
                end: d("2000-02-23")
            }
        );
        assert_eq!(
            e("2011/2015-01"),
            Epoch {
                start: d("2011-01-01"),
                end: d("2015-02-01")
            }
        );
        let t = d("2011-02-11") + 10 * 3600 + 30 * 60;
        for s in [
            "2011-02-11T10:30:00Z",
            "2011-02-11T11:30:00+01:00",
            "2011-02-11T10:30:00",
            "2011:02:11 10:30:00",
        ] {
            assert_eq!(
                e(s),
                Epoch {
                    start: t,
                    end: t + 1
                },
                "{s}"
            );
        }
        assert_eq!(
            e("2011-02-11T10:30"),
            Epoch {
                start: t,
                end: t + 1
            }
        );
        for bad in [
            "",
            "soon",
            "2011-13",
            "2011-02-30",
            "2015/2011",
            "20110211x",
        ] {
            assert!(Epoch::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn only_a_span_wholly_after_another_takes_precedence() {
        let e = |s| Epoch::parse(s).unwrap();
        assert!(e("2024").after(&e("2000-02-11/2000-02-22")));
        assert!(!e("2000").after(&e("2024")));
        // The same year, or spans that overlap: neither saw the ground last.
        assert!(!e("2011-06").after(&e("2011")));
        assert!(!e("2011").after(&e("2011-06")));
        assert!(e("2011-07").after(&e("2011-06")));
        assert_eq!(
            e("2000-02-11/2000-02-22").to_string(),
            "2000-02-11/2000-02-22"
        );
        assert_eq!(e("2011-02-11").to_string(), "2011-02-11");
    }
}
