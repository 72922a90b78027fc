//! Schema migrations, one file per step. See README.md in this folder for the rules.
//!
//! This file is compiled as a child of `src/store/migrate.rs`, so `super` is that module.

use super::Step;

mod v0_to_v1;
mod v1_to_v2;
mod v2_to_v3;
mod v3;
mod v3_to_v4;
mod v4_to_v5;
mod v5_to_v6;
mod v6_to_v7;
mod v7_to_v8;

/// Every step, as (from version, to version, step). `migrate` follows them from the version a
/// store records up to `migrate::CURRENT`.
pub(super) const STEPS: &[(u32, u32, Step)] = &[
    (0, 1, v0_to_v1::run),
    (1, 2, v1_to_v2::run),
    (2, 3, v2_to_v3::run),
    (3, 4, v3_to_v4::run),
    (4, 5, v4_to_v5::run),
    (5, 6, v5_to_v6::run),
    (6, 7, v6_to_v7::run),
    (7, 8, v7_to_v8::run),
];
