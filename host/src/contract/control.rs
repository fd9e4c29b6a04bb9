//! Standard control strings: the one language of motion commands, spoken by
//! behaviours, operators, the arbiter and the translators
//! (`docs/control-strings.md`).
//!
//! ```text
//! command = "STOP"
//!         | "VEL"  SP number SP number     ; linear m/s, angular rad/s (counter-clockwise +)
//!         | "GOTO" SP number SP number     ; goal x, y in metres (world frame)
//! number  = a finite decimal: [+-] digits [. digits] [e [+-] digits]
//! SP      = one or more spaces or tabs; leading and trailing blanks are allowed
//! ```
//!
//! Keywords are case-insensitive; [`ControlCommand`]'s `Display` writes the
//! canonical form (upper case, single spaces, shortest exact numbers), which
//! parses back to the same command.
//!
//! Between components a command travels as a [`Command`]: parsed once where
//! it enters (a guest's emit, an operator's line, a recording, a bridge),
//! carried with the text it entered as, and formatted only where a guest or a
//! log reads a command the host made (the arbiter's STOP, the envelope's
//! scaled speed). The grammar lives in the contract because the host's
//! `Value` carries it.

use std::borrow::Cow;
use std::fmt;
use std::sync::Arc;

use crate::contract::clip;

/// Longest control string accepted: a command is a keyword and two numbers;
/// anything longer is garbage or an attack on the parser.
pub const MAX_CONTROL_STRING_LEN: usize = 128;

/// A parsed control string.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ControlCommand {
    /// Stop the motors now.
    Stop,
    /// Drive at `linear` m/s forward and `angular` rad/s counter-clockwise.
    Vel { linear: f64, angular: f64 },
    /// Go to the point (`x`, `y`) in metres, world frame (for planners).
    Goto { x: f64, y: f64 },
}

impl ControlCommand {
    /// Whether this command lets the robot move.
    pub fn is_stop(&self) -> bool {
        matches!(self, ControlCommand::Stop)
            || matches!(self, ControlCommand::Vel { linear, angular } if *linear == 0.0 && *angular == 0.0)
    }
}

impl fmt::Display for ControlCommand {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ControlCommand::Stop => f.write_str("STOP"),
            // `{:?}` is the shortest text that parses back to the same f64, and
            // switches to exponents for huge and tiny values.
            ControlCommand::Vel { linear, angular } => write!(f, "VEL {linear:?} {angular:?}"),
            ControlCommand::Goto { x, y } => write!(f, "GOTO {x:?} {y:?}"),
        }
    }
}

/// A motion command as it travels between components: the parsed command
/// (or why the text did not parse), and the text it entered as. Cloning is
/// cheap (the text is shared).
#[derive(Clone, Debug)]
pub enum Command {
    /// A command the host made (the arbiter's STOP, the envelope's scaled
    /// speed): its text is formatted when a guest or a log reads it.
    Made(ControlCommand),
    /// A command as it entered the host, parsed there once.
    Entered { text: Arc<str>, parsed: Result<ControlCommand, Arc<ControlParseError>> },
}

impl Command {
    /// Parses `text` once; an invalid text travels as such, so each reader
    /// decides what it means (the arbiter ignores it, the envelope stops).
    pub fn parse(text: &str) -> Command {
        Command::Entered { text: Arc::from(text), parsed: parse(text).map_err(Arc::new) }
    }

    /// The command, or why its text did not parse.
    pub fn parsed(&self) -> Result<ControlCommand, &ControlParseError> {
        match self {
            Command::Made(command) => Ok(*command),
            Command::Entered { parsed, .. } => parsed.as_ref().map(|c| *c).map_err(|e| e.as_ref()),
        }
    }

    /// The command when its text parsed.
    pub fn motion(&self) -> Option<ControlCommand> {
        self.parsed().ok()
    }

    /// The text as it entered, or the canonical form of a command the host
    /// made (formatted here, when a guest or a log reads it).
    pub fn text(&self) -> Cow<'_, str> {
        match self {
            Command::Made(command) => Cow::Owned(command.to_string()),
            Command::Entered { text, .. } => Cow::Borrowed(text),
        }
    }
}

impl From<ControlCommand> for Command {
    /// A command the host made: its text is formatted when it is read.
    fn from(command: ControlCommand) -> Command {
        Command::Made(command)
    }
}

impl From<&str> for Command {
    fn from(text: &str) -> Command {
        Command::parse(text)
    }
}

impl From<String> for Command {
    fn from(text: String) -> Command {
        Command::parse(&text)
    }
}

/// Two commands are equal when they read the same: the same text.
impl PartialEq for Command {
    fn eq(&self, other: &Command) -> bool {
        self.text() == other.text()
    }
}

impl PartialEq<ControlCommand> for Command {
    fn eq(&self, other: &ControlCommand) -> bool {
        self.motion().as_ref() == Some(other)
    }
}

impl fmt::Display for Command {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.text())
    }
}

/// Why a control string did not parse, and where (1-based character column).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("column {column}: {message}")]
pub struct ControlParseError {
    pub column: usize,
    pub message: String,
}

impl std::str::FromStr for ControlCommand {
    type Err = ControlParseError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        parse(text)
    }
}

/// Builds a command from its (up to two) numbers.
type Build = fn(f64, f64) -> ControlCommand;

/// Parses one control string.
pub fn parse(text: &str) -> Result<ControlCommand, ControlParseError> {
    if text.len() > MAX_CONTROL_STRING_LEN {
        return Err(error(
            MAX_CONTROL_STRING_LEN + 1,
            format!("control string longer than {MAX_CONTROL_STRING_LEN} bytes"),
        ));
    }
    let words = words(text);
    let Some(&(keyword_column, keyword)) = words.first() else {
        return Err(error(1, "empty control string: expected STOP, VEL or GOTO".to_string()));
    };
    let (arguments, command): (&[&str], Build) = match keyword.to_ascii_uppercase().as_str() {
        "STOP" => (&[], |_, _| ControlCommand::Stop),
        "VEL" => (&["linear speed (m/s)", "angular speed (rad/s)"], |linear, angular| ControlCommand::Vel {
            linear,
            angular,
        }),
        "GOTO" => (&["goal x (m)", "goal y (m)"], |x, y| ControlCommand::Goto { x, y }),
        _ => {
            return Err(error(
                keyword_column,
                format!("unknown command '{}': expected STOP, VEL or GOTO", clip(keyword)),
            ));
        }
    };
    let mut values = [0.0; 2];
    for (i, what) in arguments.iter().enumerate() {
        let Some(&(column, word)) = words.get(i + 1) else {
            let end = text.trim_end().chars().count() + 1;
            return Err(error(end, format!("missing the {what}")));
        };
        values[i] = parse_number(word)
            .ok_or_else(|| error(column, format!("expected the {what} as a finite number, found '{}'", clip(word))))?;
    }
    if let Some(&(column, word)) = words.get(arguments.len() + 1) {
        return Err(error(column, format!("unexpected '{}' after the command", clip(word))));
    }
    Ok(command(values[0], values[1]))
}

/// Words with their 1-based character columns.
fn words(text: &str) -> Vec<(usize, &str)> {
    let mut words = Vec::new();
    let mut start: Option<(usize, usize)> = None;
    for (column, (byte, c)) in text.char_indices().enumerate() {
        let blank = c == ' ' || c == '\t';
        match (blank, start) {
            (false, None) => start = Some((column + 1, byte)),
            (true, Some((col, from))) => {
                words.push((col, &text[from..byte]));
                start = None;
            }
            _ => {}
        }
    }
    if let Some((col, from)) = start {
        words.push((col, &text[from..]));
    }
    words
}

fn parse_number(word: &str) -> Option<f64> {
    let valid = word.chars().all(|c| c.is_ascii_digit() || matches!(c, '+' | '-' | '.' | 'e' | 'E'));
    word.parse::<f64>().ok().filter(|x| valid && x.is_finite())
}

fn error(column: usize, message: String) -> ControlParseError {
    ControlParseError { column, message }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn good_strings_parse() {
        let cases = [
            ("STOP", ControlCommand::Stop),
            ("  stop\t", ControlCommand::Stop),
            ("VEL 0.2 -0.5", ControlCommand::Vel { linear: 0.2, angular: -0.5 }),
            ("vel  1e-1\t+3", ControlCommand::Vel { linear: 0.1, angular: 3.0 }),
            ("GOTO 4 2.5", ControlCommand::Goto { x: 4.0, y: 2.5 }),
        ];
        for (text, expected) in cases {
            assert_eq!(parse(text), Ok(expected), "{text}");
        }
    }

    #[test]
    fn bad_strings_name_the_column() {
        let cases = [
            ("", "column 1: empty control string: expected STOP, VEL or GOTO"),
            ("JUMP 1", "column 1: unknown command 'JUMP': expected STOP, VEL or GOTO"),
            ("VEL 0.2", "column 8: missing the angular speed (rad/s)"),
            ("VEL x 0", "column 5: expected the linear speed (m/s) as a finite number, found 'x'"),
            ("VEL 0 inf", "column 7: expected the angular speed (rad/s) as a finite number, found 'inf'"),
            ("VEL 0 NaN", "column 7: expected the angular speed (rad/s) as a finite number, found 'NaN'"),
            ("STOP now", "column 6: unexpected 'now' after the command"),
            ("GOTO 1 2 3", "column 10: unexpected '3' after the command"),
            ("  VEL 1e999 0", "column 7: expected the linear speed (m/s) as a finite number, found '1e999'"),
        ];
        for (text, expected) in cases {
            assert_eq!(parse(text).map_err(|e| e.to_string()), Err(expected.to_string()), "{text:?}");
        }
        let long = format!("VEL 1 {}", "0".repeat(200));
        assert!(parse(&long).is_err_and(|e| e.message.contains("longer than")));
    }

    /// Formats generated commands and parses them back.
    #[test]
    fn format_then_parse_round_trips() {
        let mut state: u64 = 0x9e37_79b9_7f4a_7c15;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for _ in 0..20_000 {
            let a = f64::from_bits(next());
            let b = (next() as i64 as f64) / 1e6;
            let (a, b) = (if a.is_finite() { a } else { 0.5 }, b);
            let command = match next() % 3 {
                0 => ControlCommand::Stop,
                1 => ControlCommand::Vel { linear: a, angular: b },
                _ => ControlCommand::Goto { x: b, y: a },
            };
            let text = command.to_string();
            assert_eq!(parse(&text), Ok(command), "{text}");
        }
    }

    /// A command keeps the text it entered as; one the host made is
    /// formatted when read; an invalid one keeps its text and its error.
    #[test]
    fn a_command_reads_as_it_entered() {
        let entered = Command::parse("VEL 0.2 0");
        assert_eq!(
            (entered.text().as_ref(), entered.motion()),
            ("VEL 0.2 0", Some(ControlCommand::Vel { linear: 0.2, angular: 0.0 }))
        );
        assert_eq!(entered.to_string(), "VEL 0.2 0");
        assert_eq!(Command::from(ControlCommand::Vel { linear: 0.2, angular: 0.0 }).text(), "VEL 0.2 0.0");
        let invalid = Command::parse("FLY 1");
        assert_eq!(invalid.text(), "FLY 1");
        assert!(invalid.parsed().is_err_and(|e| e.column == 1));
        assert!(entered == ControlCommand::Vel { linear: 0.2, angular: 0.0 } && invalid != ControlCommand::Stop);
    }
}
