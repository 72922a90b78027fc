//! The `folder` backend: an object store's layout in a folder of a local or mounted disk,
//! through `object_store`'s `LocalFileSystem`, with the one operation it lacks.
//!
//! The writer's lease (see [`super::lease`]) is renewed, and taken over once it ran out, with a
//! PUT that succeeds only if the object is still the version the writer last saw
//! (`PutMode::Update`, S3's `If-Match`). `LocalFileSystem` answers that with "not
//! implemented": a writer on a folder could not renew its lease, so it stopped writing once
//! the lease ran out (15 s by default), and a store whose writer stopped after that could not
//! be opened again, its expired lease being one nobody could take over. Here the compare and
//! the write run under an exclusive lock on a file beside the objects (`flock`, which every
//! process of the host, and NFS v4 clients, honour): the object's entity tag (its inode,
//! size and modification time) is compared with the version seen, and the new version is
//! written as every `LocalFileSystem` PUT is, to a temporary file renamed over the object.
//! Everything else goes to `LocalFileSystem` unchanged.

use async_trait::async_trait;
use futures::stream::BoxStream;
use futures::TryStreamExt;
use object_store::local::LocalFileSystem;
use object_store::path::Path as ObjectPath;
use object_store::{
    CopyOptions, GetOptions, GetResult, ListResult, MultipartUpload, ObjectMeta, ObjectStore,
    ObjectStoreExt, PutMode, PutMultipartOptions, PutOptions, PutPayload, PutResult, RenameOptions,
    Result, UpdateVersion,
};
use std::fs::{File, OpenOptions};
use std::path::{Path, PathBuf};

/// The lock file the conditional writes take, in the folder's root. Not an object: listings
/// leave it out.
pub const LOCK_FILE: &str = ".conditional-writes.lock";

fn is_lock(m: &ObjectMeta) -> bool {
    m.location.as_ref() == LOCK_FILE
}

/// A folder laid out as an object store, with conditional updates.
#[derive(Debug)]
pub struct Folder {
    inner: LocalFileSystem,
    lock: PathBuf,
}

impl Folder {
    /// The object store in `dir`, which must exist.
    pub fn new(dir: &Path) -> Result<Folder> {
        Ok(Folder {
            inner: LocalFileSystem::new_with_prefix(dir)?,
            lock: dir.join(LOCK_FILE),
        })
    }

    /// The exclusive lock under which an update compares and writes; released when the file
    /// it returns is closed.
    async fn exclusive(&self) -> Result<File> {
        let path = self.lock.clone();
        let locked = tokio::task::spawn_blocking(move || {
            let f = OpenOptions::new()
                .create(true)
                .truncate(false)
                .write(true)
                .open(&path)?;
            fs2::FileExt::lock_exclusive(&f)?;
            Ok::<_, std::io::Error>(f)
        })
        .await;
        let generic = |e: Box<dyn std::error::Error + Send + Sync>| object_store::Error::Generic {
            store: "folder",
            source: e,
        };
        match locked {
            Ok(Ok(f)) => Ok(f),
            Ok(Err(e)) => Err(generic(Box::new(e))),
            Err(e) => Err(generic(Box::new(e))),
        }
    }

    /// `PutMode::Update`: the write goes through only if `location` is still at `seen`.
    async fn update(
        &self,
        location: &ObjectPath,
        payload: PutPayload,
        opts: PutOptions,
        seen: UpdateVersion,
    ) -> Result<PutResult> {
        let _locked = self.exclusive().await?;
        let stale = |why: String| object_store::Error::Precondition {
            path: location.to_string(),
            source: why.into(),
        };
        match self.inner.head(location).await {
            Ok(now) if now.e_tag == seen.e_tag => {}
            Ok(now) => {
                return Err(stale(format!(
                    "the object is at version {:?}, not {:?}",
                    now.e_tag, seen.e_tag
                )))
            }
            // Gone since it was seen: not the version the writer holds either.
            Err(object_store::Error::NotFound { .. }) => {
                return Err(stale("the object is gone".into()))
            }
            Err(e) => return Err(e),
        }
        let opts = PutOptions {
            mode: PutMode::Overwrite,
            ..opts
        };
        self.inner.put_opts(location, payload, opts).await
    }
}

impl std::fmt::Display for Folder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Folder({})", self.inner)
    }
}

#[async_trait]
impl ObjectStore for Folder {
    async fn put_opts(
        &self,
        location: &ObjectPath,
        payload: PutPayload,
        opts: PutOptions,
    ) -> Result<PutResult> {
        match opts.mode.clone() {
            PutMode::Update(seen) => self.update(location, payload, opts, seen).await,
            _ => self.inner.put_opts(location, payload, opts).await,
        }
    }

    async fn put_multipart_opts(
        &self,
        location: &ObjectPath,
        opts: PutMultipartOptions,
    ) -> Result<Box<dyn MultipartUpload>> {
        self.inner.put_multipart_opts(location, opts).await
    }

    async fn get_opts(&self, location: &ObjectPath, options: GetOptions) -> Result<GetResult> {
        self.inner.get_opts(location, options).await
    }

    async fn get_ranges(
        &self,
        location: &ObjectPath,
        ranges: &[std::ops::Range<u64>],
    ) -> Result<Vec<bytes::Bytes>> {
        self.inner.get_ranges(location, ranges).await
    }

    fn delete_stream(
        &self,
        locations: BoxStream<'static, Result<ObjectPath>>,
    ) -> BoxStream<'static, Result<ObjectPath>> {
        self.inner.delete_stream(locations)
    }

    fn list(&self, prefix: Option<&ObjectPath>) -> BoxStream<'static, Result<ObjectMeta>> {
        Box::pin(
            self.inner
                .list(prefix)
                .try_filter(|m| futures::future::ready(!is_lock(m))),
        )
    }

    fn list_with_offset(
        &self,
        prefix: Option<&ObjectPath>,
        offset: &ObjectPath,
    ) -> BoxStream<'static, Result<ObjectMeta>> {
        Box::pin(
            self.inner
                .list_with_offset(prefix, offset)
                .try_filter(|m| futures::future::ready(!is_lock(m))),
        )
    }

    async fn list_with_delimiter(&self, prefix: Option<&ObjectPath>) -> Result<ListResult> {
        let mut listed = self.inner.list_with_delimiter(prefix).await?;
        listed.objects.retain(|m| !is_lock(m));
        Ok(listed)
    }

    async fn copy_opts(
        &self,
        from: &ObjectPath,
        to: &ObjectPath,
        options: CopyOptions,
    ) -> Result<()> {
        self.inner.copy_opts(from, to, options).await
    }

    async fn rename_opts(
        &self,
        from: &ObjectPath,
        to: &ObjectPath,
        options: RenameOptions,
    ) -> Result<()> {
        self.inner.rename_opts(from, to, options).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn version(r: &PutResult) -> UpdateVersion {
        UpdateVersion {
            e_tag: r.e_tag.clone(),
            version: r.version.clone(),
        }
    }

    fn update(v: &UpdateVersion) -> PutOptions {
        PutMode::Update(v.clone()).into()
    }

    /// An update goes through from the version last seen only: once, from one writer of two
    /// that saw the same version, and not at all once the object is gone.
    #[tokio::test]
    async fn an_update_goes_through_only_from_the_version_last_seen() {
        let tmp = tempfile::tempdir().unwrap();
        let f = Folder::new(tmp.path()).unwrap();
        let at = ObjectPath::from("lease");
        let first = f.put(&at, "a".into()).await.unwrap();
        let second = f
            .put_opts(&at, "b".into(), update(&version(&first)))
            .await
            .expect("the version seen");
        let again = f.put_opts(&at, "c".into(), update(&version(&first))).await;
        assert!(
            matches!(again, Err(object_store::Error::Precondition { .. })),
            "{again:?}"
        );
        let got = f.get(&at).await.unwrap().bytes().await.unwrap();
        assert_eq!(&got[..], b"b");
        // Two writers that both saw `second`: one wins.
        let seen = version(&second);
        let (x, y) = tokio::join!(
            f.put_opts(&at, "x".into(), update(&seen)),
            f.put_opts(&at, "y".into(), update(&seen))
        );
        assert!(x.is_ok() != y.is_ok(), "{x:?} {y:?}");
        f.delete(&at).await.unwrap();
        let gone = f.put_opts(&at, "z".into(), update(&seen)).await;
        assert!(
            matches!(gone, Err(object_store::Error::Precondition { .. })),
            "{gone:?}"
        );
        // The lock file is no object of the store.
        let listed: Vec<_> = f.list(None).try_collect().await.unwrap();
        assert!(listed.is_empty(), "{listed:?}");
        let listed = f.list_with_delimiter(None).await.unwrap();
        assert!(listed.objects.is_empty(), "{listed:?}");
    }
}
