//! File-system helpers: writes that keep what the user configured safe on
//! a crash without ever replacing what is not a regular file, and
//! [`HiddenPaths`], the server folders no answer spells out.

use std::fs::{File, FileType};
use std::io::Write;
use std::os::unix::fs::FileTypeExt;
use std::path::{Path, PathBuf};

/// Why a path is not written: it is there and is neither a regular file
/// nor a character device or FIFO (a directory, a socket, a block device).
/// Replacing it would lose it; writing into a block device would write a
/// disk.
#[derive(Debug, thiserror::Error)]
#[error(
    "{path} is {what}: a file is written only at a new path, over a regular file, or into a character device or FIFO (as /dev/null, /dev/stdout)"
)]
pub struct NotAFile {
    pub path: PathBuf,
    pub what: &'static str,
}

/// How a path is written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    /// A new path or a regular file: a file beside it, renamed over it.
    Replace,
    /// A character device or a FIFO (`/dev/null`, `/dev/stdout` on a pipe
    /// or a terminal): written straight into, never replaced.
    Stream,
}

/// What writing `path` would do, following symbolic links (`/dev/stdout`);
/// an `InvalidInput` error carrying [`NotAFile`] for anything else that is
/// there.
pub fn target_of(path: &Path) -> std::io::Result<Target> {
    match std::fs::metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Target::Replace),
        Err(e) => Err(e),
        Ok(meta) => target_of_type(path, meta.file_type()),
    }
}

fn target_of_type(path: &Path, kind: FileType) -> std::io::Result<Target> {
    let what = if kind.is_file() {
        return Ok(Target::Replace);
    } else if kind.is_char_device() || kind.is_fifo() {
        return Ok(Target::Stream);
    } else if kind.is_dir() {
        "a directory"
    } else if kind.is_socket() {
        "a socket"
    } else if kind.is_block_device() {
        "a block device"
    } else {
        "not a file"
    };
    Err(std::io::Error::new(std::io::ErrorKind::InvalidInput, NotAFile { path: path.to_path_buf(), what }))
}

/// Opens a character device or FIFO for writing (waiting for a FIFO's
/// reader), without creating or truncating, and checks that what was
/// opened is still one.
fn open_stream(path: &Path) -> std::io::Result<File> {
    let file = std::fs::OpenOptions::new().write(true).open(path)?;
    match target_of_type(path, file.metadata()?.file_type())? {
        Target::Stream => Ok(file),
        Target::Replace => Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{} became a regular file while it was opened", path.display()),
        )),
    }
}

/// Opens `path` for a long write (a recording): a new path or a regular
/// file is created or truncated, a character device or FIFO is written
/// into, anything else refused ([`target_of`]). Returns the file and its
/// target.
pub fn create_output(path: &Path) -> std::io::Result<(File, Target)> {
    match target_of(path)? {
        Target::Replace => Ok((File::create(path)?, Target::Replace)),
        Target::Stream => Ok((open_stream(path)?, Target::Stream)),
    }
}

/// Writes `bytes` to `path` so that a crash at any moment leaves either the
/// old file or the new one: a temporary file in the same directory is
/// written, fsynced and renamed over `path`, then the directory is fsynced.
/// A character device or FIFO at `path` is written straight into (renaming
/// over `/dev/null` would replace the device); anything else there is
/// refused ([`target_of`]).
pub fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    prepare_atomically(path, bytes)?.commit()
}

/// The first half of [`write_atomically`]: the bytes are written to a
/// temporary file beside `path` and fsynced, so whatever could fail for
/// want of room has failed by now; [`PreparedWrite::commit`] renames it
/// into place. Dropped uncommitted, the temporary file is removed and
/// `path` is untouched. For a character device or FIFO the bytes wait in
/// memory and `commit` writes them in.
pub fn prepare_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<PreparedWrite> {
    if target_of(path)? == Target::Stream {
        return Ok(PreparedWrite(Prepared::Stream { path: path.to_path_buf(), bytes: bytes.to_vec() }));
    }
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    let mut file = tempfile::NamedTempFile::new_in(dir)?;
    file.write_all(bytes)?;
    file.as_file().sync_all()?;
    Ok(PreparedWrite(Prepared::Replace { file, path: path.to_path_buf(), dir: dir.to_path_buf() }))
}

/// A file written beside its place and fsynced, waiting to be renamed in
/// (or bytes waiting for their character device or FIFO).
#[derive(Debug)]
pub struct PreparedWrite(Prepared);

#[derive(Debug)]
enum Prepared {
    Replace { file: tempfile::NamedTempFile, path: PathBuf, dir: PathBuf },
    Stream { path: PathBuf, bytes: Vec<u8> },
}

impl PreparedWrite {
    /// Renames the file into place and fsyncs the directory; or writes
    /// the bytes into the device or FIFO. A path that became something
    /// else meanwhile is refused.
    pub fn commit(self) -> std::io::Result<()> {
        match self.0 {
            Prepared::Replace { file, path, dir } => {
                if target_of(&path)? == Target::Stream {
                    return open_stream(&path)?.write_all(&std::fs::read(file.path())?);
                }
                file.persist(&path).map_err(|e| e.error)?;
                File::open(&dir)?.sync_all()
            }
            Prepared::Stream { path, bytes } => open_stream(&path)?.write_all(&bytes),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replaces_the_file_and_leaves_no_temporary_behind() -> std::io::Result<()> {
        let dir = tempfile::tempdir()?;
        let path = dir.path().join("report.json");
        write_atomically(&path, b"old")?;
        write_atomically(&path, b"new")?;
        assert_eq!(std::fs::read(&path)?, b"new");
        assert_eq!(std::fs::read_dir(dir.path())?.count(), 1);
        Ok(())
    }

    #[test]
    fn a_prepared_write_changes_nothing_until_committed() -> std::io::Result<()> {
        let dir = tempfile::tempdir()?;
        let path = dir.path().join("state.json");
        write_atomically(&path, b"old")?;
        drop(prepare_atomically(&path, b"dropped")?);
        assert_eq!(std::fs::read(&path)?, b"old");
        assert_eq!(std::fs::read_dir(dir.path())?.count(), 1);
        let prepared = prepare_atomically(&path, b"new")?;
        assert_eq!(std::fs::read(&path)?, b"old");
        prepared.commit()?;
        assert_eq!(std::fs::read(&path)?, b"new");
        assert_eq!(std::fs::read_dir(dir.path())?.count(), 1);
        Ok(())
    }

    fn mkfifo(path: &Path) {
        let made = std::process::Command::new("mkfifo").arg(path).status();
        assert!(made.is_ok_and(|s| s.success()), "mkfifo {}", path.display());
    }

    #[test]
    fn a_fifo_gets_the_bytes_and_stays_a_fifo() -> std::io::Result<()> {
        let dir = tempfile::tempdir()?;
        let fifo = dir.path().join("out");
        mkfifo(&fifo);
        let reader = {
            let fifo = fifo.clone();
            std::thread::spawn(move || std::fs::read(&fifo))
        };
        write_atomically(&fifo, b"through the pipe")?;
        assert_eq!(reader.join().map_err(|_| std::io::Error::other("reader panicked"))??, b"through the pipe");
        assert!(std::fs::metadata(&fifo)?.file_type().is_fifo());
        assert_eq!(std::fs::read_dir(dir.path())?.count(), 1, "no temporary file left");
        Ok(())
    }

    #[test]
    fn a_character_device_is_written_into_and_stays_one() -> std::io::Result<()> {
        let dir = tempfile::tempdir()?;
        // The null device's numbers, in a folder of the test's own (as
        // root): never the real /dev/null.
        let null = dir.path().join("null");
        let made = std::process::Command::new("mknod").arg(&null).args(["c", "1", "3"]).status()?;
        assert!(made.success(), "mknod needs root");
        write_atomically(&null, b"gone")?;
        prepare_atomically(&null, b"gone")?.commit()?;
        let (mut file, target) = create_output(&null)?;
        assert_eq!(target, Target::Stream);
        file.write_all(b"gone")?;
        assert!(std::fs::symlink_metadata(&null)?.file_type().is_char_device());
        assert_eq!(std::fs::read_dir(dir.path())?.count(), 1, "no temporary file left");
        Ok(())
    }

    #[test]
    fn a_directory_a_socket_and_a_block_device_are_refused_and_left_as_they_were() -> std::io::Result<()> {
        let dir = tempfile::tempdir()?;
        let folder = dir.path().join("folder");
        std::fs::create_dir(&folder)?;
        let socket = dir.path().join("socket");
        let _listener = std::os::unix::net::UnixListener::bind(&socket)?;
        // A block device node the test makes (as root), for a loop device
        // minor that no one uses: were it ever opened, it would fail.
        let block = dir.path().join("block");
        let made = std::process::Command::new("mknod").arg(&block).args(["b", "7", "254"]).status()?;
        assert!(made.success(), "mknod needs root");
        for (path, what) in [(&folder, "a directory"), (&socket, "a socket"), (&block, "a block device")] {
            let before = std::fs::symlink_metadata(path)?.file_type();
            for result in [write_atomically(path, b"x"), prepare_atomically(path, b"x").map(drop)] {
                let error = result.err().unwrap_or_else(|| panic!("{} was written", path.display()));
                assert_eq!(error.kind(), std::io::ErrorKind::InvalidInput);
                let message = error.to_string();
                assert!(message.starts_with(&format!("{} is {what}:", path.display())), "{message}");
            }
            assert!(create_output(path).is_err(), "{} opened", path.display());
            assert_eq!(std::fs::symlink_metadata(path)?.file_type(), before);
        }
        assert!(std::fs::read_dir(&folder)?.next().is_none());
        assert_eq!(std::fs::read_dir(dir.path())?.count(), 3, "no temporary file left");
        Ok(())
    }
}

/// Server folders an answer to a remote user must not spell out (the
/// store, the compile cache, the robot file's folder, the working folder),
/// each with the name shown instead; longest first, so a folder inside
/// another is named by its own name.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct HiddenPaths(Vec<(String, &'static str)>);

impl HiddenPaths {
    /// `paths` (folder, what to show instead), each as given and as its
    /// canonical form. Folders shorter than two components are left
    /// alone: hiding `/` would rewrite every path-like text.
    pub fn new(paths: &[(&Path, &'static str)]) -> HiddenPaths {
        let mut hidden: Vec<(String, &'static str)> = paths
            .iter()
            .flat_map(|(path, shown)| {
                let canonical = std::fs::canonicalize(path).ok();
                [Some(path.to_path_buf()), canonical].into_iter().flatten().map(move |p| (p, *shown))
            })
            .filter(|(p, _)| p.is_absolute() && p.components().count() > 2)
            .map(|(p, shown)| (p.display().to_string().trim_end_matches('/').to_string(), shown))
            .collect();
        hidden.sort_by(|a, b| b.0.len().cmp(&a.0.len()).then_with(|| a.0.cmp(&b.0)));
        hidden.dedup();
        HiddenPaths(hidden)
    }

    /// Whether there is nothing to hide.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// `bytes` with every hidden folder replaced by its name (for text
    /// that need not be UTF-8: a log line, a file served as it is).
    pub fn hide_bytes<'b>(&self, bytes: &'b [u8]) -> std::borrow::Cow<'b, [u8]> {
        let mut out = std::borrow::Cow::Borrowed(bytes);
        for (path, shown) in &self.0 {
            let needle = path.as_bytes();
            if !out.windows(needle.len()).any(|w| w == needle) {
                continue;
            }
            let mut replaced = Vec::with_capacity(out.len());
            let mut rest: &[u8] = &out;
            while let Some(at) = rest.windows(needle.len()).position(|w| w == needle) {
                replaced.extend_from_slice(&rest[..at]);
                replaced.extend_from_slice(shown.as_bytes());
                rest = &rest[at + needle.len()..];
            }
            replaced.extend_from_slice(rest);
            out = std::borrow::Cow::Owned(replaced);
        }
        out
    }

    /// Replaces every hidden folder in `text` by its name.
    pub fn hide(&self, text: &mut String) {
        for (path, shown) in &self.0 {
            if text.contains(path.as_str()) {
                *text = text.replace(path.as_str(), shown);
            }
        }
    }
}

#[cfg(test)]
mod hidden_tests {
    use super::*;

    #[test]
    fn a_folder_inside_another_is_named_by_its_own_name_and_short_ones_are_left_alone() {
        let hidden = HiddenPaths::new(&[
            (Path::new("/srv/robot"), "<robot file folder>"),
            (Path::new("/srv/robot/store"), "<store>"),
            (Path::new("/srv"), "<too short>"),
        ]);
        let mut text =
            r#"{"source": "/srv/robot/store/blobs/ab", "config": "/srv/robot/mine.xml", "at": "/srv/x"}"#.to_string();
        let bytes = hidden.hide_bytes(text.as_bytes()).into_owned();
        hidden.hide(&mut text);
        assert_eq!(text, r#"{"source": "<store>/blobs/ab", "config": "<robot file folder>/mine.xml", "at": "/srv/x"}"#);
        assert_eq!(bytes, text.as_bytes());
        assert_eq!(
            hidden.hide_bytes(b"\xff/srv/robot/a \xfe/srv/robot/b").as_ref(),
            b"\xff<robot file folder>/a \xfe<robot file folder>/b"
        );
    }
}
