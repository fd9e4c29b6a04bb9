//! The `subsume lab` commands docs/lab.md shows, as the tests that run
//! them against a robot (`deploy::every_lab_command_docs_lab_md_shows_...`)
//! and against a lab server (`labnet::every_lab_command_docs_lab_md_...`)
//! read them: taken from the document's `sh` blocks, their placeholders
//! filled with the test's own, split into words as a shell would.

use std::path::{Path, PathBuf};

/// One command of the document.
pub(crate) struct DocCommand {
    /// The `## ` section it is shown in ("Several robots", ...).
    pub(crate) section: String,
    /// The command as written: its continuation lines joined, its `#`
    /// comment cut.
    pub(crate) text: String,
}

impl DocCommand {
    /// `subsume lab serve ...`, which starts a lab server rather than
    /// talking to one.
    pub(crate) fn serves(&self) -> bool {
        self.text.starts_with("subsume lab serve")
    }
}

/// Every `subsume lab ...` command in docs/lab.md's `sh` blocks, in the
/// document's order.
pub(crate) fn lab_commands() -> Vec<DocCommand> {
    let doc = std::fs::read_to_string(crate::support::repo_root().join("docs/lab.md")).unwrap();
    let mut commands = Vec::new();
    let mut section = String::new();
    let mut in_block = false;
    let mut in_sh = false;
    let mut pending = String::new();
    for line in doc.lines() {
        if line.starts_with("```") {
            in_block = !in_block;
            in_sh = line == "```sh";
            continue;
        }
        if !in_block {
            if let Some(heading) = line.strip_prefix("## ") {
                section = heading.trim().to_string();
            }
            continue;
        }
        if !in_sh {
            continue;
        }
        let line = line.split(" #").next().unwrap_or_default().trim_end();
        if let Some(head) = line.strip_suffix('\\') {
            pending.push_str(head);
            continue;
        }
        let whole = format!("{pending}{line}");
        pending.clear();
        if whole.trim().starts_with("subsume lab ") {
            commands.push(DocCommand { section: section.clone(), text: whole.trim().to_string() });
        }
    }
    commands
}

/// What the test puts for the document's placeholders.
pub(crate) struct Filling<'a> {
    /// The portal's address, for `HOST` and `https://robot.example.org`.
    pub(crate) host: &'a str,
    /// The folder the commands run in; `DIR`, `kit` and the results go
    /// under it.
    pub(crate) work: &'a Path,
    /// `NAME=FILE.wasm` for the document's `planner=...planner.wasm`.
    pub(crate) component: &'a str,
    /// For the document's `--duration 60`.
    pub(crate) duration_s: &'a str,
    /// For the document's experiment `ID`.
    pub(crate) id: u64,
}

/// A command with its placeholders filled, in words.
pub(crate) struct Filled {
    pub(crate) words: Vec<String>,
    /// `COMMAND > FILE`: the file its output goes into, as the shell would.
    pub(crate) into: Option<PathBuf>,
    /// The line run, for messages.
    pub(crate) line: String,
}

impl Filled {
    /// The `lab` subcommand (`submit`, `list`, ...).
    pub(crate) fn subcommand(&self) -> &str {
        &self.words[2]
    }
}

/// `command` (the `n`th of the document) with `filling`'s values.
pub(crate) fn fill(command: &DocCommand, n: usize, filling: &Filling) -> Filled {
    let work = filling.work;
    let line = command
        .text
        .replace("https://robot.example.org", filling.host)
        .replace(" HOST", &format!(" {}", filling.host))
        .replace(" ID ", &format!(" {} ", filling.id))
        .replace(" DIR", &format!(" {}", work.join(format!("dir-{n}")).display()))
        .replace("-o kit", &format!("-o {}", work.join("kit").display()))
        .replace("--results results/turns", &format!("--results {}", work.join("turns").display()))
        .replace("planner=target/wasm32-wasip2/release/planner.wasm", filling.component)
        .replace("--duration 60", &format!("--duration {}", filling.duration_s));
    let (line, into) = match line.split_once(" > ") {
        Some((command, file)) => (command.to_string(), Some(work.join(file.trim()))),
        None => (line.clone(), None),
    };
    Filled { words: shell_words(&line), into, line }
}

/// `line` split as a shell splits it: spaces, and double quotes around a
/// word with spaces (all the document uses).
pub(crate) fn shell_words(line: &str) -> Vec<String> {
    let mut words = Vec::new();
    let mut word = String::new();
    let mut quoted = false;
    for c in line.chars() {
        match c {
            '"' => quoted = !quoted,
            ' ' if !quoted => {
                if !word.is_empty() {
                    words.push(std::mem::take(&mut word));
                }
            }
            c => word.push(c),
        }
    }
    if !word.is_empty() {
        words.push(word);
    }
    words
}
