//! The one rule by which a coordinate counts as on a line: a grid line, or the line halfway
//! between two samples. The CPU resampler, the edge patches' nearest-sample rule and the
//! shader all decide with it, so that a point on a line gets one answer whichever of them
//! asks.

/// How close to a line, in cells, a coordinate counts as on it: far below any sample spacing
/// a request can ask for, far above the rounding of a position carried through a georeference.
pub const SNAP: f64 = 1e-9;

/// Whether an offset `d` from a line, in cells, puts a point on it: strictly within [`SNAP`].
#[inline]
pub fn on_line(d: f64) -> bool {
    d.abs() < SNAP
}

/// A grid coordinate, moved onto the nearest grid line when it is [`on_line`] there.
#[inline]
pub fn snap(x: f64) -> f64 {
    let n = x.round();
    if on_line(x - n) {
        n
    } else {
        x
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_coordinate_within_snap_of_a_line_is_on_it_and_one_further_is_not() {
        assert_eq!(snap(3.0 + 0.5 * SNAP), 3.0);
        assert_eq!(snap(3.0 - 0.5 * SNAP), 3.0);
        assert_ne!(snap(3.0 + 2.0 * SNAP), 3.0);
        assert!(on_line(0.0) && !on_line(SNAP) && !on_line(-SNAP));
    }
}
