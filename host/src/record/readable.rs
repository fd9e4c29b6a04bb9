//! What of a recording the `mcap` crate may be given: the bytes up to the
//! first record it would panic on, and a panic ends `subsume run`
//! (`run::stop_motors_on_panic`). Both found by the `mcap_replay` fuzz
//! target in `mcap` 0.26: a record's length is added to its header size
//! without a check, so a length near `u64::MAX` wraps; an attachment whose
//! body is shorter than its header and CRC is sliced backwards. Pure (the
//! fuzz target compiles it).

/// An MCAP file's first bytes.
const MAGIC: &[u8] = b"\x89MCAP0\r\n";
/// A record's opcode (1 byte) and length (8 bytes, little-endian).
const RECORD_HEADER: usize = 1 + 8;
const CHUNK: u8 = 0x06;
const ATTACHMENT: u8 = 0x09;

/// The part of a recording `mcap` may read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Readable<'a> {
    /// The magic and the records before the first unsound one.
    pub bytes: &'a [u8],
    /// Where the bytes were cut (the first unsound record's offset), if
    /// they were: the reader treats the file as ending early there.
    pub cut_at: Option<usize>,
}

/// `bytes` (a file that starts with the MCAP magic) up to its first record
/// whose length runs past the file, or, inside an uncompressed chunk, past
/// the chunk (then the whole chunk goes).
pub fn readable(bytes: &[u8]) -> Readable<'_> {
    let mut at = MAGIC.len().min(bytes.len());
    while at < bytes.len() {
        let sound = match record(bytes, at) {
            Some((opcode, body)) => is_sound(opcode, body),
            // Only part of a header left: the file ends early there, as the
            // reader says by itself.
            None if bytes.len() - at < RECORD_HEADER => break,
            None => false,
        };
        if !sound {
            return Readable { bytes: &bytes[..at], cut_at: Some(at) };
        }
        at += RECORD_HEADER + record(bytes, at).map_or(0, |(_, body)| body.len());
    }
    Readable { bytes, cut_at: None }
}

/// The opcode and body of the record at `at`, if its length fits.
fn record(bytes: &[u8], at: usize) -> Option<(u8, &[u8])> {
    let header = bytes.get(at..at.checked_add(RECORD_HEADER)?)?;
    let len = usize::try_from(u64::from_le_bytes(header[1..].try_into().ok()?)).ok()?;
    let start = at + RECORD_HEADER;
    Some((header[0], bytes.get(start..start.checked_add(len)?)?))
}

/// Whether `mcap` reads the record without a panic (its length fits: the
/// caller checked that).
fn is_sound(opcode: u8, body: &[u8]) -> bool {
    match opcode {
        CHUNK => chunk_is_sound(body),
        ATTACHMENT => attachment_is_sound(body),
        _ => true,
    }
}

/// Whether an attachment's body holds its header (log and create time,
/// name, media type, data length) and its CRC.
fn attachment_is_sound(body: &[u8]) -> bool {
    let text_end = |at: usize| -> Option<usize> {
        let len = body.get(at..at.checked_add(4)?)?;
        at.checked_add(4)?.checked_add(usize::try_from(u32::from_le_bytes(len.try_into().ok()?)).ok()?)
    };
    let header_len = text_end(8 + 8).and_then(text_end).and_then(|at| at.checked_add(8));
    header_len.and_then(|len| len.checked_add(4)).is_some_and(|len| len <= body.len())
}

/// Whether every record of an uncompressed chunk fits in it (a compressed
/// chunk the reader refuses by itself: it has no decompressor).
fn chunk_is_sound(body: &[u8]) -> bool {
    // Start and end time, uncompressed size (u64 each), CRC (u32).
    let fixed = 8 + 8 + 8 + 4;
    let Some(len) = body.get(fixed..fixed + 4) else { return false };
    let Ok(compression_len) = usize::try_from(u32::from_le_bytes([len[0], len[1], len[2], len[3]])) else {
        return false;
    };
    let Some(records_at) = (fixed + 4).checked_add(compression_len) else { return false };
    let Some(compression) = body.get(fixed + 4..records_at) else { return false };
    let Some(size) = body.get(records_at..records_at + 8) else { return false };
    let Ok(size) = usize::try_from(u64::from_le_bytes(size.try_into().unwrap_or([0; 8]))) else { return false };
    let Some(records) = (records_at + 8).checked_add(size).and_then(|end| body.get(records_at + 8..end)) else {
        return false;
    };
    if !compression.is_empty() {
        return true;
    }
    let mut at = 0;
    while at < records.len() {
        let Some((opcode, inner)) = record(records, at) else { return false };
        if !is_sound(opcode, inner) {
            return false;
        }
        at += RECORD_HEADER + inner.len();
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record_bytes(opcode: u8, body: &[u8]) -> Vec<u8> {
        [&[opcode][..], &(body.len() as u64).to_le_bytes(), body].concat()
    }

    fn chunk(records: &[u8]) -> Vec<u8> {
        let mut body = vec![0; 8 + 8 + 8 + 4];
        body.extend_from_slice(&0u32.to_le_bytes());
        body.extend_from_slice(&(records.len() as u64).to_le_bytes());
        body.extend_from_slice(records);
        record_bytes(CHUNK, &body)
    }

    #[test]
    fn sound_files_are_whole_and_a_length_past_the_end_cuts_there() {
        let header = record_bytes(0x01, b"\0\0\0\0\0\0\0\0");
        let message = record_bytes(0x05, b"0123456789abcdef");
        let good = [MAGIC, &header, &chunk(&message), &message].concat();
        assert_eq!(readable(&good), Readable { bytes: &good, cut_at: None });
        // A record whose length is u64::MAX: what made mcap panic.
        let mut huge = record_bytes(0x05, b"");
        huge[1..9].copy_from_slice(&u64::MAX.to_le_bytes());
        let bad = [&good[..], &huge, &message].concat();
        assert_eq!(readable(&bad), Readable { bytes: &good, cut_at: Some(good.len()) });
        // The same inside a chunk: the chunk goes.
        let start = MAGIC.len() + header.len();
        let bad_chunk = [MAGIC, &header, &chunk(&[&message[..], &huge].concat()), &message].concat();
        assert_eq!(readable(&bad_chunk), Readable { bytes: &bad_chunk[..start], cut_at: Some(start) });
        // An attachment too short for its header and CRC, at the top and
        // in a chunk.
        let short = record_bytes(ATTACHMENT, &[0; 8 + 8 + 4 + 4 + 8]);
        let attachment = record_bytes(ATTACHMENT, &[0; 8 + 8 + 4 + 4 + 8 + 4]);
        let with = [&good[..], &attachment, &short].concat();
        assert_eq!(
            readable(&with),
            Readable { bytes: &with[..good.len() + attachment.len()], cut_at: Some(good.len() + attachment.len()) }
        );
        let in_chunk = [MAGIC, &header, &chunk(&short)].concat();
        assert_eq!(readable(&in_chunk).cut_at, Some(start));
        // A file cut inside a record header is left to the reader.
        let cut = &good[..good.len() - message.len() + 3];
        assert_eq!(readable(cut).cut_at, None);
    }
}
