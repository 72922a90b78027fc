//! 8 → 9: a survey's record keeps what its sidecar says of where it came from (title,
//! licence, attribution, acquisition), so that a height can name its source and a map its
//! attribution. The step rewrites each `s/` record with those left unsaid; a survey's sidecar
//! is read again, and its record written with them, when its file is next ingested.

use super::v8::SurveyV8;
use super::Ctx;
use crate::form::Survey;
use crate::{decode, encode, keys};

pub(super) fn run(tree: &sled::Tree, _: &Ctx) -> Result<sled::Batch, String> {
    let mut b = sled::Batch::default();
    for kv in tree.scan_prefix(keys::SURVEY_PREFIX) {
        let (k, v) = kv.map_err(|e| e.to_string())?;
        let what = format!("survey record {}", String::from_utf8_lossy(&k));
        let old: SurveyV8 = match decode(&v, &what) {
            Ok(r) => r,
            // Already in the version-9 form: a record that a later writer put in a store
            // still marked older (a store made for a test, say) is left as it is.
            Err(e) => match decode::<Survey>(&v, &what) {
                Ok(_) => continue,
                Err(_) => return Err(e.to_string()),
            },
        };
        b.insert(k, encode(&old.now()).map_err(|e| e.to_string())?);
    }
    Ok(b)
}
