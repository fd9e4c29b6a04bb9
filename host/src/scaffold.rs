//! `subsume new`: creates a component project for Rust, C, Python or
//! JavaScript from the templates in `templates/`, which are embedded in the
//! binary. Owns the list of files each language's project gets, their
//! placeholders (`{{name}}`, `{{wasm}}`, ...), and the rules on project names.
//!
//! Every project gets a copy of `wit/robot.wit` (the contract it is built
//! against, always the one this host speaks), a `robot.xml` that runs it on
//! the simulated robot, and a README. A Rust project also gets a copy of the
//! guest SDK (`guest-components/rust/sdk`), since the SDK is not published:
//! the project builds anywhere, without this repository.
//!
//! The project is written into a temporary folder beside its destination and
//! renamed into place when complete, so a failure leaves nothing behind; an
//! existing destination is refused, never written into.

use std::fmt::Write as _;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use thiserror::Error;

use crate::contract::{MAX_NAME_LEN, clip, is_valid_name};
use crate::fsutil::write_atomically;

/// The languages `subsume new` has templates for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Language {
    Rust,
    C,
    Python,
    Js,
}

impl Language {
    pub const ALL: [Language; 4] = [Language::Rust, Language::C, Language::Python, Language::Js];

    /// The name `--lang` takes.
    pub fn name(self) -> &'static str {
        match self {
            Language::Rust => "rust",
            Language::C => "c",
            Language::Python => "python",
            Language::Js => "js",
        }
    }

    fn title(self) -> &'static str {
        match self {
            Language::Rust => "Rust",
            Language::C => "C",
            Language::Python => "Python",
            Language::Js => "JavaScript",
        }
    }

    /// The one command, run in the project's folder, that builds the component.
    pub fn build_command(self) -> &'static str {
        match self {
            Language::Rust => "cargo build --release",
            Language::C | Language::Python | Language::Js => "make",
        }
    }

    /// The CPU-time budget per call the project's `robot.xml` gives its
    /// component. Compiled languages: 5 ms, hundreds of times what their
    /// calls take. Interpreted ones (CPython, SpiderMonkey): 50 ms, room for
    /// their slower first calls and garbage collection, and still half the
    /// default stall limit (100 ms).
    pub fn budget(self) -> &'static str {
        match self {
            Language::Rust | Language::C => "5ms",
            Language::Python | Language::Js => "50ms",
        }
    }

    /// The contract the language's template is written against (the
    /// project's `wit/robot.wit`).
    fn contract(self) -> &'static str {
        match self {
            Language::C => WIT_0_1,
            Language::Rust | Language::Python | Language::Js => WIT_CURRENT,
        }
    }

    /// Where the build leaves the component, relative to the project.
    pub fn wasm_path(self, name: &str) -> String {
        match self {
            Language::Rust => format!("target/wasm32-wasip2/release/{}.wasm", name.replace('-', "_")),
            Language::C | Language::Python | Language::Js => format!("{name}.wasm"),
        }
    }

    /// The file holding the component's code.
    fn source(self) -> &'static str {
        match self {
            Language::Rust => "src/lib.rs",
            Language::C => "app.c",
            Language::Python => "app.py",
            Language::Js => "app.js",
        }
    }

    /// What the README says the build needs.
    fn needs(self) -> &'static str {
        match self {
            Language::Rust => {
                "Needs Rust with the `wasm32-wasip2` target (`rustup target add wasm32-wasip2`). The guest SDK \
                 is in `sdk/`, a copy made by `subsume new` (it is not on crates.io); wit-bindgen comes from \
                 crates.io."
            }
            Language::C => {
                "Needs clang, wasm-ld and wasi-libc (Debian: `apt-get install clang lld wasi-libc \
                 libclang-rt-dev-wasm32`), wit-bindgen's C generator and wasm-tools (`cargo install --locked \
                 wit-bindgen-cli@0.46.0 --no-default-features --features c` and `cargo install --locked \
                 wasm-tools@1.239.0 --no-default-features --features component`), and cargo once more, to \
                 fetch the WASI adapter into `build/`."
            }
            Language::Python => {
                "Needs python3 with venv (Debian: `apt-get install python3-venv`). The first build makes \
                 `.venv/` with componentize-py 0.25.1 from PyPI."
            }
            Language::Js => {
                "Needs node 20 or newer with npm. The first build installs componentize-js 0.23.0 from npm \
                 into `node_modules/`."
            }
        }
    }

    /// The language's own files: (path in the project, template text).
    fn files(self) -> &'static [(&'static str, &'static str)] {
        match self {
            Language::Rust => &[
                ("Cargo.toml", include_str!("../../templates/rust/Cargo.toml")),
                (".cargo/config.toml", include_str!("../../guest-components/rust/.cargo/config.toml")),
                (".gitignore", include_str!("../../templates/rust/gitignore")),
                ("src/lib.rs", include_str!("../../templates/rust/src/lib.rs")),
                ("sdk/Cargo.toml", include_str!("../../templates/rust/sdk/Cargo.toml")),
            ],
            Language::C => &[
                ("Makefile", include_str!("../../templates/c/Makefile")),
                (".gitignore", include_str!("../../templates/c/gitignore")),
                ("app.c", include_str!("../../templates/c/app.c")),
            ],
            Language::Python => &[
                ("Makefile", include_str!("../../templates/python/Makefile")),
                (".gitignore", include_str!("../../templates/python/gitignore")),
                ("app.py", include_str!("../../templates/python/app.py")),
            ],
            Language::Js => &[
                ("Makefile", include_str!("../../templates/js/Makefile")),
                (".gitignore", include_str!("../../templates/js/gitignore")),
                ("package.json", include_str!("../../templates/js/package.json")),
                ("app.js", include_str!("../../templates/js/app.js")),
            ],
        }
    }
}

impl FromStr for Language {
    type Err = ScaffoldError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        Language::ALL.into_iter().find(|l| l.name() == text).ok_or_else(|| ScaffoldError::UnknownLanguage(clip(text)))
    }
}

impl std::fmt::Display for Language {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Files every project gets, whatever its language.
const COMMON_FILES: [(&str, &str); 3] = [
    ("README.md", include_str!("../../templates/common/README.md")),
    ("robot.xml", include_str!("../../templates/common/robot.xml")),
    ("arena.world", include_str!("../../templates/common/arena.world")),
];

/// The contract a project is built against, as `wit/robot.wit`: the Rust
/// SDK and the Python and JavaScript templates speak 0.2.0; the C template
/// is still written against 0.1.0, which the host keeps running.
const WIT_CURRENT: &str = include_str!("../../wit/robot.wit");
const WIT_0_1: &str = include_str!("../../wit/0.1.0/robot.wit");

/// The Rust guest SDK, copied into Rust projects as `sdk/src/lib.rs`.
const SDK_SOURCE: &str = include_str!("../../guest-components/rust/sdk/src/lib.rs");
/// The SDK's other module (`pub mod drive;` in lib.rs): a project without
/// it does not build.
const SDK_DRIVE: &str = include_str!("../../guest-components/rust/sdk/src/drive.rs");
/// Where the SDK finds the WIT files in this repository, and in a project.
const SDK_WIT_PATH: (&str, &str) = ("path: \"../../../wit\"", "path: \"../wit\"");

/// A project's files and folder are the user's own, readable like any
/// source tree (temporary files are created private).
const FILE_MODE: u32 = 0o644;
const DIR_MODE: u32 = 0o755;

/// Names a project may not take although they fit the component-name rule:
/// Rust keywords and names cargo reserves (a Rust project would not build),
/// and the SDK's own crate name.
const RESERVED_NAMES: &[&str] = &[
    "abstract",
    "alloc",
    "as",
    "async",
    "await",
    "become",
    "box",
    "break",
    "build",
    "const",
    "continue",
    "core",
    "crate",
    "deps",
    "do",
    "dyn",
    "else",
    "enum",
    "examples",
    "extern",
    "false",
    "final",
    "fn",
    "for",
    "gen",
    "if",
    "impl",
    "in",
    "incremental",
    "let",
    "loop",
    "macro",
    "match",
    "mod",
    "move",
    "mut",
    "override",
    "priv",
    "proc-macro",
    "proc_macro",
    "pub",
    "ref",
    "return",
    "self",
    "static",
    "std",
    "struct",
    "subsume-guest",
    "subsume_guest",
    "super",
    "test",
    "trait",
    "true",
    "try",
    "type",
    "typeof",
    "unsafe",
    "unsized",
    "use",
    "virtual",
    "where",
    "while",
    "yield",
];

#[derive(Debug, Error)]
pub enum ScaffoldError {
    #[error("project name '{name}' {why}")]
    InvalidName { name: String, why: String },
    #[error("unknown language '{0}' (expected rust, c, python or js)")]
    UnknownLanguage(String),
    #[error("'{}' already exists; subsume new never writes into an existing directory", .0.display())]
    Exists(PathBuf),
    #[error("failed to create project '{}': {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// The trial run `subsume new` suggests and the project's README shows:
/// without the portal (`--http off`), so it runs beside a host whose portal
/// holds the default port (the demo's, say) instead of failing to listen.
pub const TRIAL_COMMAND: &str = "subsume run robot.xml --http off --duration 30 --report report.json";

/// A project `create` made.
#[derive(Clone, Debug)]
pub struct Project {
    pub name: String,
    pub language: Language,
    /// The project's folder.
    pub dir: PathBuf,
    /// Every file written, relative to `dir`.
    pub files: Vec<PathBuf>,
}

impl Project {
    /// Where the documented build command leaves the component.
    pub fn wasm(&self) -> PathBuf {
        self.dir.join(self.language.wasm_path(&self.name))
    }

    /// What to do next, for a person.
    pub fn next_steps(&self) -> String {
        let mut text = String::new();
        let _ = writeln!(
            text,
            "created {}: a {} component named '{}'",
            self.dir.display(),
            self.language.title(),
            self.name
        );
        let _ = writeln!(text, "  cd {}", self.dir.display());
        let _ =
            writeln!(text, "  {}    # builds {}", self.language.build_command(), self.language.wasm_path(&self.name));
        let _ = writeln!(text, "  subsume describe {}", self.language.wasm_path(&self.name));
        let _ = writeln!(text, "  {TRIAL_COMMAND}    # no portal: the demo's may hold 127.0.0.1:8080");
        let _ = writeln!(text, "{} is yours to change; README.md says more.", self.language.source());
        text
    }
}

/// Checks a project name: a component name (`[a-z][a-z0-9_-]*`, at most
/// [`MAX_NAME_LEN`]) that no language's tools refuse.
pub fn check_name(name: &str) -> Result<(), ScaffoldError> {
    let why = if !is_valid_name(name) {
        format!("is not [a-z][a-z0-9_-]* of at most {MAX_NAME_LEN} characters")
    } else if RESERVED_NAMES.contains(&name) {
        "is reserved (a Rust keyword or a name cargo keeps for itself)".to_string()
    } else {
        return Ok(());
    };
    Err(ScaffoldError::InvalidName { name: clip(name), why })
}

/// The files of a `language` project named `name`: (path, contents).
pub fn render(name: &str, language: Language) -> Vec<(String, String)> {
    let wasm = language.wasm_path(name);
    let vars = [
        ("{{name}}", name),
        ("{{lang}}", language.title()),
        ("{{build}}", language.build_command()),
        ("{{wasm}}", wasm.as_str()),
        ("{{source}}", language.source()),
        ("{{needs}}", language.needs()),
        ("{{budget}}", language.budget()),
        ("{{trial}}", TRIAL_COMMAND),
    ];
    let fill = |text: &str| vars.iter().fold(text.to_string(), |text, (key, value)| text.replace(key, value));
    let mut files: Vec<(String, String)> =
        COMMON_FILES.iter().chain(language.files()).map(|(path, text)| (path.to_string(), fill(text))).collect();
    let wit = language.contract();
    files.push(("wit/robot.wit".to_string(), wit.to_string()));
    if language == Language::Rust {
        files.push(("sdk/src/lib.rs".to_string(), SDK_SOURCE.replace(SDK_WIT_PATH.0, SDK_WIT_PATH.1)));
        files.push(("sdk/src/drive.rs".to_string(), SDK_DRIVE.to_string()));
    }
    files
}

/// Creates a `language` project named `name` in `dir` (default: `./NAME`),
/// which must not exist.
pub fn create(name: &str, language: Language, dir: Option<&Path>) -> Result<Project, ScaffoldError> {
    check_name(name)?;
    let dir = dir.map_or_else(|| PathBuf::from(name), Path::to_path_buf);
    if dir.symlink_metadata().is_ok() {
        return Err(ScaffoldError::Exists(dir));
    }
    let io = |source| ScaffoldError::Io { path: dir.clone(), source };
    let parent = match dir.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => parent.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(io)?;
    let staging = tempfile::Builder::new().prefix(".subsume-new-").tempdir_in(&parent).map_err(io)?;
    let mut files = Vec::new();
    for (path, text) in render(name, language) {
        let target = staging.path().join(&path);
        if let Some(folder) = target.parent() {
            std::fs::create_dir_all(folder).map_err(io)?;
        }
        write_atomically(&target, text.as_bytes()).map_err(io)?;
        std::fs::set_permissions(&target, std::fs::Permissions::from_mode(FILE_MODE)).map_err(io)?;
        files.push(PathBuf::from(path));
    }
    std::fs::set_permissions(staging.path(), std::fs::Permissions::from_mode(DIR_MODE)).map_err(io)?;
    // A destination made meanwhile is still refused (rename would only
    // replace an empty one).
    if dir.symlink_metadata().is_ok() {
        return Err(ScaffoldError::Exists(dir.clone()));
    }
    let staged = staging.keep();
    if let Err(source) = std::fs::rename(&staged, &dir) {
        let _ = std::fs::remove_dir_all(&staged);
        return Err(io(source));
    }
    Ok(Project { name: name.to_string(), language, dir, files })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_must_suit_every_language() {
        for good in ["wander", "wall-follower", "a", "line_tracker2"] {
            assert!(check_name(good).is_ok(), "{good}");
        }
        let long = "a".repeat(MAX_NAME_LEN + 1);
        for bad in ["", "Wander", "2fast", "-x", "my avoider", "ünï", "../escape", "a/b", long.as_str()] {
            let err = check_name(bad).map(|()| bad).err().map(|e| e.to_string()).unwrap_or_default();
            assert!(err.contains("is not [a-z][a-z0-9_-]*"), "{bad}: {err}");
        }
        for reserved in ["fn", "test", "build", "subsume-guest"] {
            let err = check_name(reserved).map(|()| reserved).err().map(|e| e.to_string()).unwrap_or_default();
            assert!(err.contains("is reserved"), "{reserved}: {err}");
        }
    }

    #[test]
    fn languages_parse_by_name_and_unknown_ones_are_named() {
        for language in Language::ALL {
            assert_eq!(language.name().parse::<Language>().ok(), Some(language));
        }
        let err = "cobol".parse::<Language>().err().map(|e| e.to_string());
        assert_eq!(err.as_deref(), Some("unknown language 'cobol' (expected rust, c, python or js)"));
    }

    #[test]
    fn every_placeholder_is_filled_and_every_project_has_the_contract() {
        for language in Language::ALL {
            let files = render("wall-follower", language);
            for (path, text) in &files {
                assert!(!text.contains("{{"), "{language} {path} keeps a placeholder");
            }
            let file = |name: &str| files.iter().find(|(path, _)| path == name).map(|(_, text)| text.as_str());
            let contract = if language == Language::C { WIT_0_1 } else { WIT_CURRENT };
            assert_eq!(file("wit/robot.wit"), Some(contract), "{language}");
            let robot = file("robot.xml").unwrap_or_default();
            assert!(robot.contains(&format!("source=\"{}\"", language.wasm_path("wall-follower"))), "{robot}");
            assert!(robot.contains(&format!("budget=\"{}\"", language.budget())), "{robot}");
            let source = file(language.source()).unwrap_or_default();
            assert!(source.contains("\"wall-follower\"") || source.contains("'wall-follower'"), "{language}");
        }
    }

    #[test]
    fn the_rust_project_carries_the_sdk_pointed_at_its_own_wit() {
        // The component, translator and scorer worlds.
        assert_eq!(SDK_SOURCE.matches(SDK_WIT_PATH.0).count(), 3, "the SDK's generate! calls moved");
        let files = render("wander", Language::Rust);
        let sdk = files.iter().find(|(path, _)| path == "sdk/src/lib.rs").map(|(_, text)| text.as_str());
        let sdk = sdk.unwrap_or_default();
        assert_eq!(sdk.matches(SDK_WIT_PATH.1).count(), 3);
        assert!(!sdk.contains(SDK_WIT_PATH.0));
    }

    #[test]
    fn creates_the_project_whole_and_never_overwrites() -> Result<(), ScaffoldError> {
        let root = tempfile::tempdir().map_err(|source| ScaffoldError::Io { path: "tmp".into(), source })?;
        let dir = root.path().join("robots/wander");
        let project = create("wander", Language::C, Some(&dir))?;
        assert_eq!(project.wasm(), dir.join("wander.wasm"));
        for file in &project.files {
            assert!(dir.join(file).is_file(), "{}", file.display());
        }
        assert!(project.next_steps().contains("  make    # builds wander.wasm"), "{}", project.next_steps());
        // Only the project is left in its parent: no staging folder.
        assert_eq!(std::fs::read_dir(root.path().join("robots")).map(|d| d.count()).ok(), Some(1));

        std::fs::write(dir.join("app.c"), "mine").map_err(|source| ScaffoldError::Io { path: dir.clone(), source })?;
        let again = create("wander", Language::Python, Some(&dir));
        assert!(matches!(again, Err(ScaffoldError::Exists(_))), "{again:?}");
        assert_eq!(std::fs::read_to_string(dir.join("app.c")).ok().as_deref(), Some("mine"));
        let empty = root.path().join("empty");
        std::fs::create_dir(&empty).map_err(|source| ScaffoldError::Io { path: empty.clone(), source })?;
        assert!(matches!(create("wander", Language::Js, Some(&empty)), Err(ScaffoldError::Exists(_))));
        Ok(())
    }
}
