//! Diagnostics with `file:line:column` positions, and the map from byte
//! offsets in a source text to 1-based lines and columns.

use std::fmt;
use std::path::{Path, PathBuf};

/// One problem found in a file, at a position.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Diagnostic {
    pub path: PathBuf,
    /// 1-based line.
    pub line: usize,
    /// 1-based column, in characters.
    pub column: usize,
    /// Lowercase, names the thing and what is wrong with it.
    pub message: String,
}

impl fmt::Display for Diagnostic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}:{}: {}", self.path.display(), self.line, self.column, self.message)
    }
}

/// Every diagnostic found in one file; displayed one per line.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Diagnostics(pub Vec<Diagnostic>);

impl fmt::Display for Diagnostics {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, d) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{d}")?;
        }
        Ok(())
    }
}

impl std::error::Error for Diagnostics {}

/// Turns byte offsets of one source text into lines and columns, and
/// collects diagnostics against it.
#[derive(Debug)]
pub struct SourceMap<'a> {
    path: &'a Path,
    text: &'a str,
    line_starts: Vec<usize>,
}

impl<'a> SourceMap<'a> {
    pub fn new(path: &'a Path, text: &'a str) -> Self {
        let mut line_starts = vec![0];
        line_starts.extend(text.match_indices('\n').map(|(i, _)| i + 1));
        SourceMap { path, text, line_starts }
    }

    /// The 1-based line and column (in characters) of byte `offset`.
    pub fn line_column(&self, offset: usize) -> (usize, usize) {
        let offset = offset.min(self.text.len());
        let line = match self.line_starts.binary_search(&offset) {
            Ok(i) => i,
            Err(i) => i.saturating_sub(1),
        };
        let start = self.line_starts.get(line).copied().unwrap_or(0);
        let column = self.text.get(start..offset).map_or(offset - start, |s| s.chars().count());
        (line + 1, column + 1)
    }

    /// A diagnostic at byte `offset`.
    pub fn at(&self, offset: usize, message: impl Into<String>) -> Diagnostic {
        let (line, column) = self.line_column(offset);
        Diagnostic { path: self.path.to_path_buf(), line, column, message: message.into() }
    }

    /// The byte offset of `slice` inside the source text, if it is a
    /// sub-slice of it (quick-xml hands out borrowed slices of the input).
    pub fn offset_of(&self, slice: &[u8]) -> Option<usize> {
        let start = self.text.as_ptr() as usize;
        let at = slice.as_ptr() as usize;
        (at >= start && at + slice.len() <= start + self.text.len()).then(|| at - start)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_and_column_count_characters_from_one() {
        let text = "ab\nc\u{e9}d\n\nx";
        let map = SourceMap::new(Path::new("f.xml"), text);
        assert_eq!(map.line_column(0), (1, 1));
        assert_eq!(map.line_column(1), (1, 2));
        assert_eq!(map.line_column(3), (2, 1));
        // 'd' follows a two-byte character: byte 6, column 3.
        assert_eq!(map.line_column(6), (2, 3));
        assert_eq!(map.line_column(8), (3, 1));
        assert_eq!(map.line_column(9), (4, 1));
        assert_eq!(map.line_column(999), (4, 2));
    }
}
