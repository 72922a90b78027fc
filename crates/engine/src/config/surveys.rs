//! The sections that say how surveys are read and modelled: the default accuracy, what a
//! deleted file does, `[accuracy]`, `[vertical]` and `[patches]`.

use patchwork_core::model::evidence::Contradicted;
use patchwork_core::model::patch::{Blend, PatchKind, PatchLayout};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// What a file deleted from the inbox does to its survey.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OnDelete {
    /// A file deleted from the inbox retires its survey.
    Retire,
    /// The survey stays; only `patchwork retire` removes it.
    Keep,
}

/// The ε given to files with no sidecar and no `--accuracy`: a number of metres, or `"auto"`
/// to estimate it from each survey's own samples.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DefaultAccuracy {
    /// Estimate ε per patch from each survey's own samples, by how far its bilinear surface is from
    /// coarser copies of itself.
    Auto,
    /// Give every such survey this ε, in metres.
    Metres(f64),
}

impl std::str::FromStr for DefaultAccuracy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let t = s.trim();
        if t.eq_ignore_ascii_case("auto") {
            return Ok(DefaultAccuracy::Auto);
        }
        t.parse()
            .map(DefaultAccuracy::Metres)
            .map_err(|_| format!("{s:?} is neither \"auto\" nor a number of metres"))
    }
}

impl Serialize for DefaultAccuracy {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            DefaultAccuracy::Auto => s.serialize_str("auto"),
            DefaultAccuracy::Metres(m) => s.serialize_f64(*m),
        }
    }
}

impl<'de> Deserialize<'de> for DefaultAccuracy {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Number(f64),
            Text(String),
        }
        match Raw::deserialize(d)? {
            Raw::Number(m) => Ok(DefaultAccuracy::Metres(m)),
            Raw::Text(t) => t.parse().map_err(serde::de::Error::custom),
        }
    }
}

/// The `[accuracy]` section: what a new store does with accuracy claims that other surveys'
/// evidence finds false (docs/MODEL.md, "Overlaps"); an existing store keeps its own.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Accuracy {
    /// What a claim that another survey's evidence finds false gets: `distrust` holds it to no
    /// better than the other's claim plus how far it departs from it; `keep` only reports the
    /// verdicts.
    pub contradicted: Contradicted,
}

/// The `[vertical]` section: the store's vertical CRS and the geoid grids that carry heights
/// into it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Vertical {
    /// "EPSG:n" or "ellipsoidal"; unset adopts the first survey's that names one.
    pub crs: Option<String>,
    /// Geoid undulation grids, by the vertical CRS ("EPSG:n") they relate to the ellipsoid.
    pub geoids: std::collections::BTreeMap<String, PathBuf>,
    /// Whether EGM96's and EGM2008's grids are looked for in PROJ's data directories
    /// (`PROJ_DATA`, `/usr/share/proj`) when `geoids` names none for them.
    pub proj_data: bool,
}

impl Default for Vertical {
    fn default() -> Self {
        Vertical {
            crs: None,
            geoids: Default::default(),
            proj_data: true,
        }
    }
}

/// The `[patches]` section: the layout every store keeps, and the kind and blend of a new
/// store.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Patches {
    /// Kernel side in cells.
    pub kernel: usize,
    /// Extension zone around the kernel, in cells.
    pub margin: usize,
    /// What a new store's patches evaluate; an existing store keeps its own.
    pub kind: PatchKind,
    /// How a new store blends its patches into heights; an existing store keeps its own.
    pub blend: Blend,
}

impl Default for Patches {
    fn default() -> Self {
        let l = PatchLayout::default();
        Patches {
            kernel: l.kernel,
            margin: l.margin,
            kind: PatchKind::default(),
            blend: Blend::default(),
        }
    }
}

impl Patches {
    /// The kernel and margin of every patch, as the store lays them out.
    pub fn layout(&self) -> PatchLayout {
        PatchLayout {
            kernel: self.kernel,
            margin: self.margin,
        }
    }
}
