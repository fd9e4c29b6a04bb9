// The driver shared by the translator targets (translator_create2,
// translator_roboclaw, translator_odrive): a session of polls and bytes from
// the controller, decoded once with each stretch of bytes in one call and
// once cut into pieces. Included by each target.
//
// Input: [options][cuts] then stretches `[len][len bytes]`, each after a poll
// (the translators expect answers only to what a poll asked). `options`
// picks one of the target's option sets; `cuts` the pieces' sizes (0: one
// byte at a time).

use subsume_guest::{Decoded, Param, Params, Translator};

/// One poll period, ns (what `now_ns` advances by between stretches).
const POLL_NS: u64 = 50_000_000;

/// The readings of a whole session and its malformed count.
struct Session {
    readings: Vec<String>,
    malformed: u32,
}

fn params(options: &[(&str, &str)]) -> Params {
    Params(options.iter().map(|(name, value)| Param { name: (*name).into(), value: (*value).into() }).collect())
}

/// Sizes of the pieces a stretch is cut into, from the `cuts` byte.
fn pieces(cuts: u8, mut len: usize) -> Vec<usize> {
    let mut sizes = Vec::new();
    let mut state = u32::from(cuts);
    while len > 0 {
        // A small linear congruential walk: sizes 1 to 16, varied.
        state = state.wrapping_mul(1_103_515_245).wrapping_add(12_345);
        let size = if cuts == 0 { 1 } else { (state >> 16) as usize % 16 + 1 }.min(len);
        sizes.push(size);
        len -= size;
    }
    sizes
}

fn run<T: Translator>(mut translator: T, stretches: &[&[u8]], cuts: Option<u8>) -> Session {
    let mut session = Session { readings: Vec::new(), malformed: 0 };
    let take = |decoded: Decoded, session: &mut Session| {
        for reading in decoded.feedback {
            let text = format!("{reading:?}");
            // Every reading is a number the robot could have: what is not
            // finite must be refused in the decoder, never handed on.
            assert!(!text.contains("NaN") && !text.contains("inf"), "a reading that is not finite: {text}");
            session.readings.push(text);
        }
        session.malformed += decoded.malformed;
    };
    for (n, stretch) in stretches.iter().enumerate() {
        let _ = translator.poll(n as u64 * POLL_NS);
        match cuts {
            None => take(translator.decode(stretch), &mut session),
            Some(cuts) => {
                let mut rest = *stretch;
                for size in pieces(cuts, stretch.len()) {
                    let (piece, tail) = rest.split_at(size);
                    take(translator.decode(piece), &mut session);
                    rest = tail;
                }
            }
        }
    }
    session
}

/// Runs one input against the translator built by `make` with one of
/// `option_sets`; `malformed_too`: the malformed count must not depend on
/// the cuts either (a decoder that counts bytes, not calls).
fn check<T: Translator>(
    data: &[u8],
    make: impl Fn(&Params) -> Result<T, String>,
    option_sets: &[&[(&str, &str)]],
    malformed_too: bool,
) {
    let [options, cuts, rest @ ..] = data else { return };
    let options = option_sets[usize::from(*options) % option_sets.len()];
    let mut stretches = Vec::new();
    let mut rest = rest;
    while let [len, tail @ ..] = rest {
        let len = usize::from(*len).min(tail.len());
        stretches.push(&tail[..len]);
        rest = &tail[len..];
    }
    let Ok(whole) = make(&params(options)).map(|t| run(t, &stretches, None)) else {
        panic!("the option set {options:?} is refused")
    };
    let Ok(cut) = make(&params(options)).map(|t| run(t, &stretches, Some(*cuts))) else { return };
    assert_eq!(whole.readings, cut.readings, "the readings depend on how the bytes were cut ({options:?})");
    if malformed_too {
        assert_eq!(whole.malformed, cut.malformed, "the malformed count depends on the cuts ({options:?})");
    }
}
