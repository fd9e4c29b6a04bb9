//! `subsume user`: manage the portal's users in the store.

use std::process::ExitCode;

use anyhow::Context as _;
use subsume::config::Platform;
use subsume::store::users::{Role, UsersError, generate_password};
use subsume::store::{Outcome, Store};

use super::Context;

/// Manage the portal's users (stored in the store's users.json).
#[derive(clap::Args)]
pub struct UserCommand {
    #[command(subcommand)]
    action: UserAction,
}

#[derive(clap::Subcommand)]
enum UserAction {
    /// Add a user; prints a generated password unless --password-stdin.
    Add {
        name: String,
        /// viewer, operator (may drive), developer (may upload and activate
        /// on its platforms) or admin.
        #[arg(long)]
        role: String,
        /// network or control (repeatable; developers need at least one).
        #[arg(long = "platform")]
        platforms: Vec<String>,
        /// Read the password from the first line of standard input.
        #[arg(long)]
        password_stdin: bool,
        /// Replace the user if it exists.
        #[arg(long)]
        replace: bool,
    },
    /// Set a new password (generated, or from standard input).
    Passwd {
        name: String,
        #[arg(long)]
        password_stdin: bool,
    },
    /// Remove a user.
    Remove { name: String },
    /// List users and their roles.
    List,
}

/// A password read from the first line of standard input, or generated
/// (then true: it must be shown once).
fn password(from_stdin: bool) -> anyhow::Result<(String, bool)> {
    if from_stdin {
        let mut line = String::new();
        std::io::stdin().read_line(&mut line).context("cannot read the password from standard input")?;
        Ok((line.trim_end_matches(['\r', '\n']).to_string(), false))
    } else {
        Ok((generate_password()?, true))
    }
}

/// Changes take the store's lock (a running portal waits for it) and leave
/// a line in the audit log.
fn audit(store: &Store, action: &str, name: &str, result: &Result<(), UsersError>) {
    if let Ok(writer) = store.lock() {
        let detail = result.as_ref().err().map(ToString::to_string).unwrap_or_default();
        let outcome = if result.is_ok() { Outcome::Ok(&detail) } else { Outcome::Refused(&detail) };
        writer.record("cli", action, &format!("user '{name}'"), outcome);
    }
}

impl UserCommand {
    pub fn execute(self, context: &Context) -> anyhow::Result<ExitCode> {
        let store = Store::open(&context.store_dir()?)?;
        match self.action {
            UserAction::Add { name, role, platforms, password_stdin, replace } => {
                let role: Role = role.parse()?;
                let platforms = platforms.iter().map(|p| Platform::parse(p)).collect::<Result<Vec<_>, _>>()?;
                let (password, generated) = password(password_stdin)?;
                let result = store.lock()?.users_mut().add(&name, role, &platforms, &password, replace);
                audit(&store, "user-add", &name, &result);
                result?;
                eprintln!("added {} '{name}' to {}", role.name(), store.users().path().display());
                if generated {
                    println!("{password}");
                    eprintln!("(that is the password; it is shown once and stored only as an argon2id hash)");
                }
            }
            UserAction::Passwd { name, password_stdin } => {
                let (password, generated) = password(password_stdin)?;
                let result = store.lock()?.users_mut().set_password(&name, &password);
                audit(&store, "user-passwd", &name, &result);
                result?;
                if generated {
                    println!("{password}");
                }
                eprintln!("new password set for '{name}'");
            }
            UserAction::Remove { name } => {
                let result = store.lock()?.users_mut().remove(&name);
                audit(&store, "user-remove", &name, &result);
                result?;
                eprintln!("removed '{name}'");
            }
            UserAction::List => {
                for u in store.users().all()? {
                    println!("{} {} {}", u.name, u.role.name(), u.platforms.join(","));
                }
            }
        }
        Ok(ExitCode::SUCCESS)
    }
}
