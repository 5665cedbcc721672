//! 3-vectors as plain `[f64; 3]` arrays: difference, sum, scaling, dot and cross products,
//! length, normalisation and the angle between two vectors. The one home of these helpers for the
//! whole crate; a module that needs them imports them from here rather than writing its own.
//!
//! Each function is the textbook expression written out component by component, in a fixed order
//! of operations (e.g. `dot` is `a0 b0 + a1 b1 + a2 b2`, summed left to right), so results are
//! reproducible to the bit. Do not reorder the arithmetic: the reconstruction and calibration
//! results, and the tests that pin them, depend on it.
//!
//! This module depends on nothing else in the crate: it is the bottom of the module order given
//! in the crate documentation (`vec3`; then `rig` and `grid`; then `geometry`; then the rest).

/// `a - b`.
#[inline]
pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `a + b`.
#[inline]
pub(crate) fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `s a`.
#[inline]
pub(crate) fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// `a . b`.
#[inline]
pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a x b` (right-handed).
#[inline]
pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Euclidean length `|a| = sqrt(a . a)`.
#[inline]
pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// `a / |a|`, each component divided by the length. The choice for new code. NaN for a zero
/// vector.
#[inline]
pub(crate) fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = norm(a);
    [a[0] / n, a[1] / n, a[2] / n]
}

/// `(1 / |a|) a`: one division, then three products. The same direction as [`normalize`] but it
/// may differ from it in the last bit of a component; light calibration ([`crate::calibrate`])
/// was written with this form and keeps it so that its results stay unchanged. NaN (or
/// infinite) for a zero vector.
#[inline]
pub(crate) fn unit(a: [f64; 3]) -> [f64; 3] {
    scale(a, 1.0 / norm(a))
}

/// Angle in radians between two vectors, `atan2(|a x b|, a . b)`: accurate also for tiny angles
/// (where `acos` of the normalised dot product loses half the digits).
#[inline]
pub(crate) fn angle(a: [f64; 3], b: [f64; 3]) -> f64 {
    norm(cross(a, b)).atan2(dot(a, b))
}

/// `!(a > b)`: whether `a` is not above `b`, true when either is NaN. The checks written with
/// it reject NaN along with the values out of range.
#[inline]
pub(crate) fn not_above(a: f64, b: f64) -> bool {
    !matches!(a.partial_cmp(&b), Some(std::cmp::Ordering::Greater))
}

/// `!(a >= b)`: whether `a` is not at least `b`, true when either is NaN.
#[inline]
pub(crate) fn not_at_least(a: f64, b: f64) -> bool {
    !matches!(
        a.partial_cmp(&b),
        Some(std::cmp::Ordering::Greater | std::cmp::Ordering::Equal)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arithmetic_is_componentwise() {
        let a = [1.0, -2.0, 3.5];
        let b = [0.5, 4.0, -1.0];
        assert_eq!(sub(a, b), [0.5, -6.0, 4.5]);
        assert_eq!(add(a, b), [1.5, 2.0, 2.5]);
        assert_eq!(scale(a, -2.0), [-2.0, 4.0, -7.0]);
        assert_eq!(dot(a, b), 0.5 - 8.0 - 3.5);
    }

    #[test]
    fn cross_is_right_handed_and_orthogonal() {
        let (x, y, z) = ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]);
        assert_eq!(cross(x, y), z);
        assert_eq!(cross(y, z), x);
        assert_eq!(cross(z, x), y);
        assert_eq!(cross(y, x), [0.0, 0.0, -1.0]);
        let (a, b) = ([1.0, 2.0, 3.0], [-4.0, 0.5, 2.0]);
        let c = cross(a, b);
        assert_eq!(dot(c, a), 0.0);
        assert_eq!(dot(c, b), 0.0);
    }

    #[test]
    fn normalisations_give_unit_length_and_keep_the_direction() {
        let a = [3.0, 0.0, -4.0];
        assert_eq!(norm(a), 5.0);
        assert_eq!(normalize(a), [0.6, 0.0, -0.8]);
        let b = [0.3, -0.2, -1.0];
        for n in [normalize(b), unit(b)] {
            assert!((norm(n) - 1.0).abs() < 1e-15);
            assert!(angle(n, b) < 1e-15);
        }
        // The two forms agree to the last bit or so, not necessarily exactly.
        let (n, u) = (normalize(b), unit(b));
        for i in 0..3 {
            assert!((n[i] - u[i]).abs() <= f64::EPSILON * n[i].abs());
        }
        assert!(normalize([0.0; 3])[0].is_nan());
    }

    #[test]
    fn angle_is_accurate_for_tiny_and_straight_angles() {
        let x = [1.0, 0.0, 0.0];
        assert_eq!(angle(x, x), 0.0);
        assert_eq!(angle(x, [0.0, 2.0, 0.0]), std::f64::consts::FRAC_PI_2);
        assert_eq!(angle(x, [-3.0, 0.0, 0.0]), std::f64::consts::PI);
        // 1e-9 rad: acos(cos t) would return 0 (cos t rounds to 1), atan2 keeps the digits.
        let t: f64 = 1e-9;
        let a = angle(x, [t.cos(), t.sin(), 0.0]);
        assert!((a - t).abs() < 1e-24, "{a}");
    }
}
