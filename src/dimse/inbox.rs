//! Where the node keeps what it receives, under `<data_dir>/dimse/`:
//!
//! - `tmp/<uuid>.part`: an instance being received (Part 10 prefix, then the data set fragments), written
//!   when it is whole or in pieces of [`SPILL`] bytes as it arrives; removed when the association aborts or
//!   the instance is refused;
//! - `incoming/<series uid>/<sop instance uid>.dcm`: complete, checked instances of a series that is still
//!   arriving (a rename from `tmp/`, so a file here is always whole);
//! - `complete/<uuid>/`: a series whose stable age passed, handed over for assembly (a rename of its
//!   `incoming/` folder, so instances arriving later start a new folder).
//!
//! After a crash, `tmp/` is emptied and every `incoming/` and `complete/` folder is picked up again.

use std::io::{self, Write as _};
use std::path::{Path, PathBuf};

/// Bytes of an instance held in memory before they are written: an instance up to this size is written,
/// synced and checked in one go, and its header is read from memory; a larger one is written in pieces
/// of this size as it arrives.
pub const SPILL: usize = 1 << 20;

/// The node's folders.
#[derive(Debug, Clone)]
pub struct Inbox {
    root: PathBuf,
}

impl Inbox {
    /// Create the folders under `data_dir` and empty `tmp/` (instances cut off by a crash).
    pub fn open(data_dir: &Path) -> io::Result<Self> {
        let root = data_dir.join("dimse");
        for sub in ["tmp", "incoming", "complete"] {
            std::fs::create_dir_all(root.join(sub))?;
        }
        for entry in std::fs::read_dir(root.join("tmp"))? {
            let entry = entry?;
            if entry.file_type()?.is_file() {
                std::fs::remove_file(entry.path())?;
            }
        }
        Ok(Self { root })
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Series folders of `incoming/` left from before a restart: (series UID, folder).
    pub fn leftover_incoming(&self) -> io::Result<Vec<(String, PathBuf)>> {
        let mut out = Vec::new();
        for entry in std::fs::read_dir(self.root.join("incoming"))? {
            let entry = entry?;
            if entry.file_type()?.is_dir() {
                out.push((
                    entry.file_name().to_string_lossy().into_owned(),
                    entry.path(),
                ));
            }
        }
        out.sort();
        Ok(out)
    }

    /// Folders of `complete/` not yet assembled (a restart came between hand-over and assembly).
    pub fn leftover_complete(&self) -> io::Result<Vec<PathBuf>> {
        let mut out = Vec::new();
        for entry in std::fs::read_dir(self.root.join("complete"))? {
            let entry = entry?;
            if entry.file_type()?.is_dir() {
                out.push(entry.path());
            }
        }
        out.sort();
        Ok(out)
    }

    /// Start receiving one instance, beginning with `prefix`; its temporary file is made when the first
    /// bytes are written.
    pub fn begin(&self, prefix: &[u8], max_bytes: u64) -> Result<InstanceSink, SinkError> {
        let path = self
            .root
            .join("tmp")
            .join(format!("{}.part", uuid::Uuid::new_v4()));
        let mut sink = InstanceSink {
            path: Some(path),
            file: None,
            buf: Vec::new(),
            spilled: false,
            written: 0,
            max_bytes,
        };
        sink.take(prefix)?;
        Ok(sink)
    }

    /// Put a received, checked instance in its series folder, replacing an earlier copy of the same
    /// instance. Both UIDs must be valid UIDs (digits and dots), which makes them safe as names. The move
    /// is durable once [`Filed::sync`] returned (the instance itself is synced before, by
    /// [`InstanceSink::finish`]).
    pub fn file(&self, temp: &Path, series_uid: &str, sop_instance_uid: &str) -> io::Result<Filed> {
        let incoming = self.root.join("incoming");
        let dir = incoming.join(series_uid);
        match std::fs::create_dir(&dir) {
            Ok(()) => sync_dir(&incoming)?,
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {}
            Err(e) => return Err(e),
        }
        let dest = dir.join(format!("{sop_instance_uid}.dcm"));
        let replaced = dest.exists();
        // The folder is opened before the rename: its handle stays valid when the series is sealed
        // (renamed) right after, so the caller may sync it outside its lock.
        let folder = std::fs::File::open(&dir)?;
        std::fs::rename(temp, &dest)?;
        Ok(Filed {
            path: dest,
            replaced,
            folder,
        })
    }

    /// Hand a series over: its `incoming/` folder becomes a new `complete/` folder.
    pub fn seal(&self, series_uid: &str) -> io::Result<PathBuf> {
        let dest = self
            .root
            .join("complete")
            .join(uuid::Uuid::new_v4().to_string());
        std::fs::rename(self.root.join("incoming").join(series_uid), &dest)?;
        Ok(dest)
    }
}

/// An instance moved into its series folder.
#[derive(Debug)]
pub struct Filed {
    pub path: PathBuf,
    /// An earlier copy of the same instance was replaced.
    pub replaced: bool,
    folder: std::fs::File,
}

impl Filed {
    /// Make the move durable: sync the series folder.
    pub fn sync(&self) -> io::Result<()> {
        sync_folder(&self.folder)
    }
}

fn sync_dir(dir: &Path) -> io::Result<()> {
    sync_folder(&std::fs::File::open(dir)?)
}

fn sync_folder(folder: &std::fs::File) -> io::Result<()> {
    match folder.sync_all() {
        // A file system that cannot sync a directory (EINVAL) keeps renames as well as it can.
        Err(e) if e.kind() == io::ErrorKind::InvalidInput => Ok(()),
        other => other,
    }
}

/// Why an instance could not be written.
#[derive(Debug, thiserror::Error)]
pub enum SinkError {
    #[error("the instance exceeds the limit of {0} bytes")]
    TooLarge(u64),
    #[error("storage: {0}")]
    Io(#[from] io::Error),
}

/// One instance being received. Dropped before [`InstanceSink::finish`], it removes its file.
#[derive(Debug)]
pub struct InstanceSink {
    path: Option<PathBuf>,
    /// Made by the first write.
    file: Option<std::fs::File>,
    /// Bytes not written yet; fewer than [`SPILL`] between calls.
    buf: Vec<u8>,
    /// Some bytes were written to the file.
    spilled: bool,
    written: u64,
    max_bytes: u64,
}

impl InstanceSink {
    /// Append bytes, writing them out (off the async threads) once [`SPILL`] are held; refuses to grow past
    /// the limit.
    pub async fn write(&mut self, bytes: &[u8]) -> Result<(), SinkError> {
        self.take(bytes)?;
        if self.buf.len() < SPILL {
            return Ok(());
        }
        let (path, file, buf) = (
            self.path.clone(),
            self.file.take(),
            std::mem::take(&mut self.buf),
        );
        let (file, buf) = tokio::task::spawn_blocking(move || {
            let mut file = open(path.as_deref(), file)?;
            file.write_all(&buf)?;
            Ok::<_, io::Error>((file, buf))
        })
        .await
        .map_err(io::Error::other)??;
        self.file = Some(file);
        self.buf = buf;
        self.buf.clear();
        self.spilled = true;
        Ok(())
    }

    /// Hold `bytes`, within the limit.
    fn take(&mut self, bytes: &[u8]) -> Result<(), SinkError> {
        self.written = self.written.saturating_add(bytes.len() as u64);
        if self.written > self.max_bytes {
            return Err(SinkError::TooLarge(self.max_bytes));
        }
        self.buf.extend_from_slice(bytes);
        Ok(())
    }

    /// Bytes taken so far (prefix included).
    pub fn written(&self) -> u64 {
        self.written
    }

    /// Write what is left and sync (blocking: call off the async threads); the file is the caller's from now
    /// on (see [`Received`]).
    pub fn finish(mut self) -> io::Result<Received> {
        let path = self
            .path
            .take()
            .ok_or_else(|| io::Error::other("instance already finished"))?;
        // From here on a failure removes the file through `received`.
        let mut received = Received {
            path: Some(path),
            bytes: None,
        };
        let mut file = open(received.path.as_deref(), self.file.take())?;
        file.write_all(&self.buf)?;
        file.sync_all()?;
        received.bytes = (!self.spilled).then(|| std::mem::take(&mut self.buf));
        Ok(received)
    }
}

/// `file`, or a new file at `path`.
fn open(path: Option<&Path>, file: Option<std::fs::File>) -> io::Result<std::fs::File> {
    match (file, path) {
        (Some(f), _) => Ok(f),
        (None, Some(p)) => std::fs::File::create(p),
        (None, None) => Err(io::Error::other("instance already finished")),
    }
}

impl Drop for InstanceSink {
    fn drop(&mut self) {
        self.file.take();
        if let Some(p) = self.path.take() {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// A whole instance in `tmp/`, not yet checked. Dropped without [`Received::keep`], it is removed.
#[derive(Debug)]
pub struct Received {
    path: Option<PathBuf>,
    /// The instance's bytes, when it was held whole in memory (no larger than [`SPILL`]).
    bytes: Option<Vec<u8>>,
}

impl Received {
    pub fn path(&self) -> &Path {
        self.path.as_deref().unwrap_or(Path::new(""))
    }

    /// The instance's bytes as written, when they were held in memory.
    pub fn bytes(&self) -> Option<&[u8]> {
        self.bytes.as_deref()
    }

    /// The file was moved elsewhere: do not remove it.
    pub fn keep(mut self) {
        self.path.take();
    }
}

impl Drop for Received {
    fn drop(&mut self) {
        if let Some(p) = self.path.take() {
            let _ = std::fs::remove_file(p);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn an_instance_dropped_midway_leaves_nothing_and_a_filed_one_is_whole() {
        let dir = tempfile::tempdir().unwrap();
        let inbox = Inbox::open(dir.path()).unwrap();
        let count = |sub: &str| std::fs::read_dir(inbox.root().join(sub)).unwrap().count();

        // Cut off before anything was written, and after a piece was.
        let mut cut = inbox.begin(b"prefix", 4 << 20).unwrap();
        cut.write(b"half of it").await.unwrap();
        assert_eq!(count("tmp"), 0);
        drop(cut);
        let mut cut = inbox.begin(b"prefix", 4 << 20).unwrap();
        cut.write(&vec![7u8; SPILL + 10]).await.unwrap();
        assert_eq!(count("tmp"), 1);
        drop(cut);
        assert_eq!(count("tmp"), 0);

        let mut whole = inbox.begin(b"AB", 1 << 20).unwrap();
        whole.write(b"CD").await.unwrap();
        let received = whole.finish().unwrap();
        assert_eq!(received.bytes(), Some(&b"ABCD"[..]));
        assert_eq!(std::fs::read(received.path()).unwrap(), b"ABCD");
        let filed = inbox.file(received.path(), "1.2.3", "1.2.3.4").unwrap();
        assert!(!filed.replaced);
        filed.sync().unwrap();
        received.keep();
        assert_eq!(std::fs::read(&filed.path).unwrap(), b"ABCD");
        assert_eq!(count("tmp"), 0);

        let sealed = inbox.seal("1.2.3").unwrap();
        assert_eq!(std::fs::read(sealed.join("1.2.3.4.dcm")).unwrap(), b"ABCD");
        assert_eq!(count("incoming"), 0);
        assert_eq!(inbox.leftover_complete().unwrap(), vec![sealed]);
    }

    #[tokio::test]
    async fn a_large_instance_is_written_in_pieces_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let inbox = Inbox::open(dir.path()).unwrap();
        let want: Vec<u8> = (0..3 * SPILL + 12_345).map(|i| (i % 251) as u8).collect();
        let mut sink = inbox.begin(&want[..100], 4 << 20).unwrap();
        // Fragments of a size that does not divide the piece.
        for part in want[100..].chunks(16_372) {
            sink.write(part).await.unwrap();
        }
        assert_eq!(sink.written(), want.len() as u64);
        let received = sink.finish().unwrap();
        assert_eq!(received.bytes(), None, "too large to be held");
        assert_eq!(std::fs::read(received.path()).unwrap(), want);
        let path = received.path().to_path_buf();
        drop(received);
        assert!(!path.exists(), "an instance not kept is removed");
    }

    #[tokio::test]
    async fn an_instance_over_the_limit_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let inbox = Inbox::open(dir.path()).unwrap();
        let mut sink = inbox.begin(b"0123", 8).unwrap();
        assert!(matches!(
            sink.write(b"45678").await,
            Err(SinkError::TooLarge(8))
        ));
        assert!(matches!(
            inbox.begin(b"012345678", 8),
            Err(SinkError::TooLarge(8))
        ));
    }
}
