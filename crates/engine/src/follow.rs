//! The engine's part in replication: a replica applies its writer's commits and publishes the
//! terrain they give, and refuses writes; a writer publishes a commit's log that could not go
//! up at once. Both run in [`rounds`], every `storage.poll_ms`.

use super::{Engine, EngineError};
use crate::restore;
use patchwork_core::geom::Aabb;
use patchwork_core::sync::{lock, read, write};
use patchwork_store::Following;
use std::sync::Arc;
use std::time::Duration;

/// Where the engine stands in replication, for `stats` without the writer.
#[derive(Clone, Debug, Default)]
pub struct Replication {
    /// The newest commit of the journal: the writer's own, or the one a replica applied.
    /// `None` on the local pack, which has no replicas.
    pub commit: Option<u64>,
    /// Set on a replica.
    pub following: Option<Following>,
}

impl Engine {
    /// The URL of the store this engine is a read replica of; `None` on the writer.
    pub fn follows(&self) -> Option<&str> {
        let url = self.cfg.storage.follow.as_str();
        (!url.is_empty()).then_some(url)
    }

    /// The region a replica of one holds and answers, in the store's plane; `None`: the whole
    /// store.
    pub fn region(&self) -> Option<&Aabb> {
        self.region.as_ref()
    }

    /// Refuses a request that reaches beyond the region of a replica of one: its answer there
    /// could lack surveys this replica does not hold. `area` is in the store's plane; `None`
    /// is a request without bounds (a view-dependent cut).
    pub(super) fn within_region(&self, area: Option<&Aabb>) -> Result<(), EngineError> {
        let Some(region) = &self.region else {
            return Ok(());
        };
        // A hair of slack for bounds carried from another CRS, which round in the last bits.
        let grown = region.grown(1e-9 * region.width().max(region.height()));
        match area {
            Some(a) if grown.contains(a) => Ok(()),
            _ => Err(EngineError::OutsideRegion {
                asked: area.copied(),
                region: *region,
            }),
        }
    }

    /// Refuses a write on a replica, naming the writer that holds the lease.
    pub(super) fn refuse_on_replica(&self) -> Result<(), EngineError> {
        if self.follows().is_none() {
            return Ok(());
        }
        match lock(&self.writer).as_ref().and_then(|s| s.refusal()) {
            Some(e) => Err(EngineError::Store(e)),
            None => Ok(()),
        }
    }

    /// Where the store stands in replication now: its newest commit, and a replica's progress and
    /// lag.
    pub fn replication(&self) -> Replication {
        read(&self.replication).clone()
    }

    /// One round: a replica applies the commits published since the last and publishes the
    /// terrain they give; a writer publishes a commit's log still waiting to go up. Returns
    /// how many commits a replica applied.
    pub fn round(&self) -> Result<u64, EngineError> {
        let mut guard = lock(&self.writer);
        let Some(store) = guard.as_mut() else {
            return Ok(0);
        };
        let before = store.commit_seq();
        let mut applied = 0;
        if store.is_replica() {
            let followed = restore::follow_up(store, self.region.as_ref());
            // Where it stands is noted even when the round failed: the lag goes on growing.
            *write(&self.replication) = super::follow::Replication {
                commit: store.commit_seq(),
                following: store.following(),
            };
            if let Some((terrain, warnings)) = followed? {
                for w in &warnings {
                    tracing::warn!(warning = %w, "the writer's commits applied with a problem");
                }
                let catalog = store.catalog()?;
                self.publish(terrain, catalog);
                applied = store.commit_seq().unwrap_or(0) - before.unwrap_or(0);
            }
        } else {
            store.publish();
        }
        write(&self.replication).commit = store.commit_seq();
        Ok(applied)
    }
}

/// Runs [`Engine::round`] every `storage.poll_ms` until `stop`; only where the store is on an
/// object store.
pub async fn rounds(engine: Arc<Engine>, mut stop: tokio::sync::watch::Receiver<bool>) {
    if engine.replication().commit.is_none() {
        return;
    }
    let every = Duration::from_millis(engine.config().storage.poll_ms);
    loop {
        tokio::select! {
            _ = tokio::time::sleep(every) => {}
            _ = stop.wait_for(|s| *s) => return,
        }
        let e = engine.clone();
        match tokio::task::spawn_blocking(move || e.round()).await {
            Ok(Ok(_)) => {}
            Ok(Err(e)) => {
                tracing::warn!(error = %e, "a replication round failed; tried again next round")
            }
            Err(e) => tracing::error!(error = %e, "a replication round panicked"),
        }
    }
}
