//! Content-derived identifiers: the same content always gets the same id, on any machine.

use serde::{Deserialize, Serialize};
use std::fmt;

macro_rules! hex_id {
    ($name:ident, $doc:literal) => {
        #[doc = $doc]
        #[derive(
            Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize,
        )]
        pub struct $name(pub u64);

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                write!(f, "{:016x}", self.0)
            }
        }

        impl std::str::FromStr for $name {
            type Err = std::num::ParseIntError;
            fn from_str(s: &str) -> Result<Self, Self::Err> {
                u64::from_str_radix(s, 16).map($name)
            }
        }
    };
}

hex_id!(
    SurveyId,
    "Identifies a survey by its samples, georeference and accuracy."
);
hex_id!(
    PatchId,
    "Identifies a patch by its survey, level and window position."
);

pub(crate) fn hash64(h: blake3::Hasher) -> u64 {
    let bytes = h.finalize();
    u64::from_le_bytes(bytes.as_bytes()[..8].try_into().expect("8 bytes"))
}

impl PatchId {
    /// The id of `survey`'s patch at `index` in the kernel tiling of level `level`.
    pub fn derive(survey: SurveyId, level: u8, index: [u32; 2]) -> Self {
        let mut h = blake3::Hasher::new();
        h.update(b"patchwork.patch.v1");
        h.update(&survey.0.to_le_bytes());
        h.update(&[level]);
        h.update(&index[0].to_le_bytes());
        h.update(&index[1].to_le_bytes());
        PatchId(hash64(h))
    }
}
