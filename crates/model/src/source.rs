//! Where samples come from when they are not in memory. The model and the terrain read
//! through this trait and do no I/O themselves; the store implements it over its chunks.

use super::grid::{Grid, SampleRect, Shape, Window};
use super::ids::SurveyId;
use thiserror::Error;

/// Samples that could not be read: the store failed, or holds something it cannot decode.
#[derive(Clone, Debug, Error, PartialEq)]
#[error("samples of survey {survey} could not be read: {reason}")]
pub struct SampleError {
    /// The survey whose samples were asked for.
    pub survey: SurveyId,
    /// What went wrong.
    pub reason: String,
    /// The samples' store could not be reached (an object store down or slow): asking again
    /// later may succeed, and nothing is known to be lost.
    pub unavailable: bool,
}

/// Refuses a rectangle that is empty or not inside a `cols × rows` level.
pub fn check_rect(
    survey: SurveyId,
    rect: &SampleRect,
    cols: usize,
    rows: usize,
) -> Result<(), SampleError> {
    if rect.is_empty() || rect.c1 > cols || rect.r1 > rows {
        return Err(SampleError {
            survey,
            reason: format!("{rect:?} is not inside a {cols}×{rows} level"),
            unavailable: false,
        });
    }
    Ok(())
}

/// Reads rectangles of the levels of stored surveys.
pub trait SampleSource: Send + Sync + std::fmt::Debug {
    /// Samples `rect` of level `level` of `survey`, whose shape is `shape`, as a grid
    /// georeferenced where they lie.
    fn read(
        &self,
        survey: SurveyId,
        level: usize,
        shape: &Shape,
        rect: SampleRect,
    ) -> Result<Grid, SampleError>;

    /// A window holding at least `rect`: what [`Self::read`] gives, or more where the source
    /// holds it already and can share it rather than copy it.
    fn window(
        &self,
        survey: SurveyId,
        level: usize,
        shape: &Shape,
        rect: SampleRect,
    ) -> Result<Window, SampleError> {
        let g = self.read(survey, level, shape, rect)?;
        Ok(Window::of(std::sync::Arc::new(g), rect, *shape))
    }

    /// Readies the samples of several reads to come, each a survey, a level, its shape and a
    /// rectangle, where the source fetches them faster together than one at a time (an object
    /// store, whose client merges neighbouring ranges into one request). Nothing it does is
    /// needed for the reads to succeed, and what it fails to fetch the read tries again and
    /// reports; but a store it could not reach at all is reported at once (`unavailable`), so
    /// that the caller does not wait out the same deadline once more for every read.
    fn prefetch(&self, wants: &[(SurveyId, usize, Shape, SampleRect)]) -> Result<(), SampleError> {
        let _ = wants;
        Ok(())
    }
}

/// Samples held in memory, by survey: a source for terrains restored without a store.
#[derive(Clone, Debug, Default)]
pub struct MemorySource {
    levels: std::collections::HashMap<SurveyId, Vec<std::sync::Arc<Grid>>>,
}

impl MemorySource {
    /// A source holding the samples of every survey given.
    pub fn of<'a>(surveys: impl IntoIterator<Item = &'a super::survey::Survey>) -> Self {
        MemorySource {
            levels: surveys
                .into_iter()
                .map(|s| (s.id, s.levels.clone()))
                .collect(),
        }
    }
}

impl SampleSource for MemorySource {
    fn read(
        &self,
        survey: SurveyId,
        level: usize,
        _: &Shape,
        rect: SampleRect,
    ) -> Result<Grid, SampleError> {
        let g = self.level(survey, level)?;
        check_rect(survey, &rect, g.cols, g.rows)?;
        Ok(g.window(rect.c0, rect.r0, rect.cols(), rect.rows()))
    }

    fn window(
        &self,
        survey: SurveyId,
        level: usize,
        _: &Shape,
        rect: SampleRect,
    ) -> Result<Window, SampleError> {
        let g = self.level(survey, level)?;
        check_rect(survey, &rect, g.cols, g.rows)?;
        Ok(Window::whole(g.clone()))
    }
}

impl MemorySource {
    fn level(&self, survey: SurveyId, level: usize) -> Result<&std::sync::Arc<Grid>, SampleError> {
        self.levels
            .get(&survey)
            .and_then(|l| l.get(level))
            .ok_or_else(|| SampleError {
                survey,
                reason: format!("no level {level} in memory"),
                unavailable: false,
            })
    }
}
