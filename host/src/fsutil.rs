//! File-system helpers: writes that keep what the user configured safe on
//! a crash, and [`HiddenPaths`], the server folders no answer spells out.

use std::io::Write;
use std::path::Path;

/// Writes `bytes` to `path` so that a crash at any moment leaves either the
/// old file or the new one: a temporary file in the same directory is
/// written, fsynced and renamed over `path`, then the directory is fsynced.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    prepare_atomically(path, bytes)?.commit()
}

/// The first half of [`write_atomically`]: the bytes are written to a
/// temporary file beside `path` and fsynced, so whatever could fail for
/// want of room has failed by now; [`PreparedWrite::commit`] renames it
/// into place. Dropped uncommitted, the temporary file is removed and
/// `path` is untouched.
pub fn prepare_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<PreparedWrite> {
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    let mut file = tempfile::NamedTempFile::new_in(dir)?;
    file.write_all(bytes)?;
    file.as_file().sync_all()?;
    Ok(PreparedWrite { file, path: path.to_path_buf(), dir: dir.to_path_buf() })
}

/// A file written beside its place and fsynced, waiting to be renamed in.
#[derive(Debug)]
pub struct PreparedWrite {
    file: tempfile::NamedTempFile,
    path: std::path::PathBuf,
    dir: std::path::PathBuf,
}

impl PreparedWrite {
    /// Renames the file into place and fsyncs the directory.
    pub fn commit(self) -> std::io::Result<()> {
        self.file.persist(&self.path).map_err(|e| e.error)?;
        std::fs::File::open(&self.dir)?.sync_all()
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
        hidden.hide(&mut text);
        assert_eq!(text, r#"{"source": "<store>/blobs/ab", "config": "<robot file folder>/mine.xml", "at": "/srv/x"}"#);
    }
}
