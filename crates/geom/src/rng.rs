//! Reproducible pseudo-random numbers, for the bench's scenes and the tests.

/// Uniform numbers in [0, 1) from a 64-bit LCG: reproducible, and enough for spreading test
/// points.
pub fn uniform(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}
