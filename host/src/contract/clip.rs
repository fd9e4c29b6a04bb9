//! The one shortener for text a guest or a remote user controls, before it
//! goes into a message or the log. Pure (no wasmtime), so the fuzz targets
//! compile it with the parsers that quote their input (fuzz/).

/// Most bytes of a guest's or a remote user's text a message quotes: enough
/// to recognise a name, while a long one cannot flood a message or a log.
pub const MAX_QUOTED_BYTES: usize = 40;

/// `text` as a message quotes it: at most [`MAX_QUOTED_BYTES`], see
/// [`clip_to`].
pub fn clip(text: &str) -> String {
    clip_to(text, MAX_QUOTED_BYTES)
}

/// The one shortener for text a guest or a remote user controls, before it
/// goes into a message or the log: at most `max_bytes` of it (cut at a
/// character boundary, then `...`), a tab replaced by a space and every
/// other control character by `?`, so the text can neither forge a log line
/// nor move a terminal's cursor.
pub fn clip_to(text: &str, max_bytes: usize) -> String {
    let mut end = text.len().min(max_bytes);
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    let shown = |c: char| match c {
        '\t' => ' ',
        c if c.is_control() => '?',
        c => c,
    };
    let mut clipped: String = text[..end].chars().map(shown).collect();
    if end < text.len() {
        clipped.push_str("...");
    }
    clipped
}
