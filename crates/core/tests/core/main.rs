//! The core's properties on synthetic and real surveys: order independence, exact retirement,
//! one answer per point and the error bound, across CRSs and where surveys meet; no store, no
//! daemon, no GPU.

mod common {
    //! The shared surveys and oracles.
    pub use patchwork_testkit::fixtures::*;

    /// A property's config: `n` cases, as few as keep `cargo test` quick, or `PROPTEST_CASES`
    /// when set (a long run). Each property names its own `n`, which would otherwise override
    /// the variable that proptest's default config reads; the rejects allowed grow with the
    /// cases, so that a long run's `prop_assume!`s do not end it.
    pub fn config(n: u32) -> proptest::test_runner::Config {
        let cases = std::env::var("PROPTEST_CASES")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(n);
        proptest::test_runner::Config {
            cases,
            max_global_rejects: cases.saturating_mul(4).max(1024),
            ..Default::default()
        }
    }
}

mod changes;
mod crs_props;
mod degradations;
mod model_props;
mod real_terrain;
mod surveys_meet;
