//! The writer's lease on an object store: one store has one writer, whichever machines its
//! database is copied to.
//!
//! The lease is an object, `<prefix>/lease`, holding who has it and until when. It is taken
//! with a PUT that succeeds only if the object is absent (`If-None-Match: *`), renewed with
//! PUTs that succeed only if it is still the version this writer last wrote (`If-Match`), and
//! taken over, once expired, the same way: of two writers that race for it, one PUT wins. A
//! writer that cannot renew stops appending when its lease runs out, before another can take
//! it over; one that finds its lease taken stops at once.

use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt, PutMode, PutPayload, UpdateVersion};
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// What the lease object holds.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Held {
    /// The writer: host, process and a random part, so that a restarted process is another
    /// writer.
    pub holder: String,
    /// When the lease runs out unless renewed, in Unix milliseconds.
    pub expires_ms: u64,
}

fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Why a lease could not be taken.
#[derive(Debug, thiserror::Error)]
pub enum LeaseError {
    /// Another writer holds it.
    #[error("{}", held_message(.0))]
    Held(Held),
    /// The object store failed. Its message is this one's, so it is not also the source.
    #[error("the lease: {0}")]
    Store(object_store::Error),
    /// The lease object is not one this version wrote.
    #[error("the lease object {path} is not one this version wrote: {why}")]
    Unreadable {
        path: String,
        why: serde_json::Error,
    },
}

fn held_message(h: &Held) -> String {
    let left = h.expires_ms.saturating_sub(now_ms());
    format!(
        "another writer, {}, holds the store's lease for {:.1} s more (until Unix time {:.3}); \
         a store has one writer",
        h.holder,
        left as f64 / 1000.0,
        h.expires_ms as f64 / 1000.0
    )
}

/// Why a writer may not append now.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Lapse {
    /// Another writer took the lease: for good.
    #[error("another writer took the store's lease")]
    Taken,
    /// The lease ran out unrenewed; writes resume once it is renewed.
    #[error(
        "the store's lease ran out (the object store could not be reached to renew it): \
         writes resume once it is renewed"
    )]
    RanOut,
}

/// The state of a lease this writer holds.
#[derive(Debug)]
struct Ours {
    version: UpdateVersion,
    /// Until when it is ours, by this machine's clock, less a margin for clocks that differ.
    until_ms: u64,
    /// Set when another writer took it.
    lost: bool,
}

/// A lease held, renewed on the caller's runtime until dropped.
#[derive(Debug)]
pub struct Lease {
    ours: Arc<Mutex<Ours>>,
    renewer: tokio::task::AbortHandle,
    /// Wakes the renewer before its next round: a commit that found the lease run out asks
    /// for it at once rather than waiting up to a third of its life.
    wake: Arc<tokio::sync::Notify>,
}

impl Drop for Lease {
    fn drop(&mut self) {
        self.renewer.abort();
    }
}

fn body(holder: &str, ttl: Duration) -> (PutPayload, u64) {
    let expires_ms = now_ms() + ttl.as_millis() as u64;
    let held = Held {
        holder: holder.to_string(),
        expires_ms,
    };
    let json = serde_json::to_vec(&held).expect("a lease serialises");
    (PutPayload::from(json), expires_ms)
}

fn version(r: &object_store::PutResult) -> UpdateVersion {
    UpdateVersion {
        e_tag: r.e_tag.clone(),
        version: r.version.clone(),
    }
}

/// The margin kept against clocks that differ between writers and the time a PUT takes.
fn margin(ttl: Duration) -> u64 {
    (ttl.as_millis() as u64 / 5).max(1)
}

/// Who holds the lease at `path` now, if anyone does and it has not run out: for a replica
/// to name the writer it refuses writes for.
pub async fn holder_of(store: Arc<dyn ObjectStore>, path: ObjectPath) -> Option<Held> {
    let got = store.get(&path).await.ok()?;
    let held: Held = serde_json::from_slice(&got.bytes().await.ok()?).ok()?;
    (held.expires_ms > now_ms()).then_some(held)
}

/// Takes the lease at `path` for `holder`, and renews it every third of `ttl` on the current
/// runtime.
pub async fn take(
    store: Arc<dyn ObjectStore>,
    path: ObjectPath,
    holder: String,
    ttl: Duration,
) -> Result<Lease, LeaseError> {
    let (payload, expires) = body(&holder, ttl);
    let put = store.put_opts(&path, payload, PutMode::Create.into()).await;
    let written = match put {
        Ok(r) => r,
        Err(object_store::Error::AlreadyExists { .. }) => {
            let got = store.get(&path).await.map_err(LeaseError::Store)?;
            let seen = UpdateVersion {
                e_tag: got.meta.e_tag.clone(),
                version: got.meta.version.clone(),
            };
            let bytes = got.bytes().await.map_err(LeaseError::Store)?;
            let held: Held =
                serde_json::from_slice(&bytes).map_err(|why| LeaseError::Unreadable {
                    path: path.to_string(),
                    why,
                })?;
            if held.expires_ms > now_ms() && !gone(&held.holder) {
                return Err(LeaseError::Held(held));
            }
            // Expired: taken over only if nobody else wrote it since it was read.
            let (payload, _) = body(&holder, ttl);
            match store
                .put_opts(&path, payload, PutMode::Update(seen).into())
                .await
            {
                Ok(r) => r,
                Err(object_store::Error::Precondition { .. }) => {
                    return Err(LeaseError::Held(Held {
                        holder: "a writer that took the expired lease first".into(),
                        expires_ms: now_ms() + ttl.as_millis() as u64,
                    }))
                }
                Err(e) => return Err(LeaseError::Store(e)),
            }
        }
        Err(e) => return Err(LeaseError::Store(e)),
    };
    let ours = Arc::new(Mutex::new(Ours {
        version: version(&written),
        until_ms: expires - margin(ttl),
        lost: false,
    }));
    let wake = Arc::new(tokio::sync::Notify::new());
    let renewer = tokio::spawn(renew(store, path, holder, ttl, ours.clone(), wake.clone()));
    Ok(Lease {
        ours,
        renewer: renewer.abort_handle(),
        wake,
    })
}

async fn renew(
    store: Arc<dyn ObjectStore>,
    path: ObjectPath,
    holder: String,
    ttl: Duration,
    ours: Arc<Mutex<Ours>>,
    wake: Arc<tokio::sync::Notify>,
) {
    let mut wait = ttl / 3;
    loop {
        tokio::select! {
            _ = tokio::time::sleep(wait) => {}
            _ = wake.notified() => {}
        }
        // After a failure, sooner: the object store may be back any moment, and writes wait
        // for the lease.
        wait = ttl / 3;
        let seen = patchwork_core::sync::lock(&ours).version.clone();
        let (payload, expires) = body(&holder, ttl);
        match store
            .put_opts(&path, payload, PutMode::Update(seen).into())
            .await
        {
            Ok(r) => {
                let mut o = patchwork_core::sync::lock(&ours);
                o.version = version(&r);
                o.until_ms = expires - margin(ttl);
            }
            Err(object_store::Error::Precondition { .. }) => {
                // A renewal that went through whose answer was lost leaves the object at a
                // version this writer has not seen: still ours if it names this writer.
                if let Ok(got) = store.get(&path).await {
                    let seen = UpdateVersion {
                        e_tag: got.meta.e_tag.clone(),
                        version: got.meta.version.clone(),
                    };
                    let mine = got.bytes().await.ok().and_then(|b| {
                        serde_json::from_slice::<Held>(&b)
                            .ok()
                            .filter(|h| h.holder == holder)
                    });
                    if mine.is_some() {
                        patchwork_core::sync::lock(&ours).version = seen;
                        continue;
                    }
                }
                tracing::error!("{}: this daemon takes no more writes", Lapse::Taken);
                patchwork_core::sync::lock(&ours).lost = true;
                return;
            }
            // Tried again at the next round; the lease runs out meanwhile if this goes on,
            // and appends stop before it does.
            Err(e) => {
                tracing::warn!(error = %e, "could not renew the store's lease");
                wait = (ttl / 3).min(Duration::from_secs(1));
            }
        }
    }
}

impl Lease {
    /// Whether another writer took the lease: for good, unlike one that ran out.
    pub fn lost(&self) -> bool {
        patchwork_core::sync::lock(&self.ours).lost
    }

    /// Asks the renewer to renew now.
    pub fn nudge(&self) {
        self.wake.notify_one();
    }

    /// Whether appends may go on: the lease is ours and has not run out.
    pub fn check(&self) -> Result<(), Lapse> {
        let o = patchwork_core::sync::lock(&self.ours);
        if o.lost {
            return Err(Lapse::Taken);
        }
        if now_ms() >= o.until_ms {
            return Err(Lapse::RanOut);
        }
        Ok(())
    }
}

/// A name for this writer: host, process and a random part.
pub fn holder() -> String {
    let mut buf = [0u8; 256];
    // SAFETY: gethostname writes at most buf.len() bytes into buf.
    let host = if unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) } == 0 {
        let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
        String::from_utf8_lossy(&buf[..end]).into_owned()
    } else {
        "unknown-host".into()
    };
    let nonce = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos())
        ^ std::process::id().rotate_left(16);
    format!("{host}:{}:{nonce:08x}", std::process::id())
}

/// Whether `holder` is a process of this host that is no longer running: a writer that
/// crashed here, whose lease a restart may take at once rather than wait out.
fn gone(holder: &str) -> bool {
    let mut parts = holder.rsplitn(3, ':');
    let (_, pid, host) = (parts.next(), parts.next(), parts.next());
    let (Some(pid), Some(host)) = (pid.and_then(|p| p.parse::<i32>().ok()), host) else {
        return false;
    };
    let me = self::holder();
    let my_host = me.rsplitn(3, ':').nth(2).unwrap_or_default();
    if host != my_host || pid == std::process::id() as i32 {
        return false;
    }
    // SAFETY: signal 0 checks that the process exists and sends nothing.
    let alive = unsafe { libc::kill(pid, 0) } == 0
        || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM);
    !alive
}
