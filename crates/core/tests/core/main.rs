//! The core's properties on synthetic and real surveys: order independence, exact retirement,
//! one answer per point and the error bound, across CRSs and where surveys meet; no store, no
//! daemon, no GPU.

mod common {
    //! The shared surveys and oracles.
    pub use patchwork_testkit::fixtures::*;
}

mod crs_props;
mod model_props;
mod real_terrain;
mod surveys_meet;
