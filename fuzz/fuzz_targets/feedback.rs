//! Motor-controller bytes: both profiles' streaming decoders take any bytes
//! in any chunking without panicking, and whatever they decode encodes to
//! bytes that decode back to the same messages.
#![no_main]
// The parser modules are shared with the host; not every item is used here.
#![allow(dead_code)]

#[path = "../../host/src/robot/protocol.rs"]
mod protocol;

use protocol::{Decoder, Message, Profile};

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Some((&split, bytes)) = data.split_first() else { return };
    for profile in [Profile::Ascii, Profile::Binary] {
        let mut decoder = Decoder::new(profile);
        let mut messages = Vec::new();
        let cut = usize::from(split).min(bytes.len());
        decoder.feed(&bytes[..cut], &mut messages);
        decoder.feed(&bytes[cut..], &mut messages);
        let mut again = Vec::new();
        for message in &messages {
            match message {
                Message::Command(c) => profile.encode_command(c, &mut again),
                Message::Feedback(f) => profile.encode_feedback(f, &mut again),
            }
        }
        let mut reread = Vec::new();
        Decoder::new(profile).feed(&again, &mut reread);
        assert_eq!(reread, messages, "{profile:?}");
    }
});
