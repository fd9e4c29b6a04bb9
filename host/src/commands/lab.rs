//! `subsume lab`: the remote lab from the command line (docs/lab.md):
//! submit an experiment and follow it to its end, list, show and cancel
//! experiments, unpack their results, unpack the lab kit, print a lab's
//! Zenoh router config. The work is `subsume::portal::lab_client`'s (and
//! `subsume::lab::router_config`'s); this file parses and prints.

use std::path::PathBuf;
use std::process::ExitCode;

use subsume::lab::router_config::{self, RouterConfigOptions};
use subsume::portal::deploy_client::{component_arg, target_arg};
use subsume::portal::lab_client::{self, Login, MaintenanceOf, Say, SubmitRequest, list_text, now_ms, show_text};
use subsume::store::experiments::{ExperimentState, Target};

use super::flags::LoginFlags;

/// Submit experiments to a robot's remote lab and follow them, list, show
/// and cancel them, download their results and the lab kit (docs/lab.md).
#[derive(clap::Args)]
pub struct LabCommand {
    #[command(subcommand)]
    action: LabAction,
}

#[derive(clap::Subcommand)]
enum LabAction {
    /// Serve a lab of several robots: its users, queue, results and
    /// portal, on no robot of its own; robots join with `subsume run ...
    /// --lab NAME` (docs/lab.md, "Several robots").
    Serve(ServeArgs),
    /// Print the Zenoh 1.10 router config (JSON5) of a lab and its robots:
    /// usrpwd auth and access control that let the lab server's user do
    /// everything under the lab's keys, each robot's user (its robot's
    /// name) only its own keys, and everyone else nothing (docs/lab.md,
    /// "A Zenoh router that lets each peer touch only its own keys").
    RouterConfig(RouterConfigArgs),
    /// Upload components and/or a robot file, stage them and submit them as
    /// an experiment, then print each state it enters until it ends: exit 0
    /// when it is `done`, 1 otherwise (with the reasons).
    Submit(SubmitArgs),
    /// List your experiments (an admin's: every one), newest first.
    List {
        /// Print the portal's records as JSON.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        login: LoginFlags,
    },
    /// Show one experiment: its states with their times and causes, its
    /// place in the queue, preflight, run, components and reasons.
    Show {
        /// The experiment's id.
        id: u64,
        /// Print the portal's record as JSON.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        login: LoginFlags,
    },
    /// Cancel an experiment (your own; an admin: any) while it waits or
    /// runs; a running one ends with the baseline back on the robot.
    Cancel {
        /// The experiment's id.
        id: u64,
        #[command(flatten)]
        login: LoginFlags,
    },
    /// Download an ended experiment's results and unpack them into a new
    /// or empty folder (every file checked against its SHA256SUMS).
    Results {
        /// The experiment's id.
        id: u64,
        /// The folder to unpack into.
        #[arg(short = 'o', long = "output", value_name = "DIR")]
        output: PathBuf,
        #[command(flatten)]
        login: LoginFlags,
    },
    /// Book the robot for a window in which only your experiments start
    /// (the owner's limits on length and time a day apply).
    Reserve {
        /// When it starts: `+MINUTES` from now, or a UTC time as
        /// `2026-11-29T10:00:00Z`.
        #[arg(long, value_name = "TIME")]
        start: String,
        /// How long it lasts, in minutes.
        #[arg(long, value_name = "MINUTES")]
        minutes: f64,
        /// Whom for (admins only; yourself by default).
        #[arg(long = "for", value_name = "USER")]
        for_user: Option<String>,
        #[command(flatten)]
        login: LoginFlags,
    },
    /// Take the robot out of service with a reason (admins): no experiment
    /// starts until `--end`; queued ones wait and are told why.
    Maintenance {
        /// Why it is out of service (shown to everyone in the queue).
        #[arg(long, value_name = "TEXT", required_unless_present = "end", conflicts_with = "end")]
        reason: Option<String>,
        /// Bring it back into service.
        #[arg(long)]
        end: bool,
        #[command(flatten)]
        login: LoginFlags,
    },
    /// Run the owner's self-test now, on the idle robot (admins): prints each
    /// check; a passed one ends a maintenance the self-test began, a failed
    /// one takes the robot out of service. Exits 1 when it fails.
    Selftest {
        #[command(flatten)]
        login: LoginFlags,
    },
    /// List the reservations not over yet, with their dates.
    Reservations {
        /// Print the portal's records as JSON.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        login: LoginFlags,
    },
    /// Cancel a reservation (your own; an admin: any).
    Unreserve {
        /// The reservation's id.
        id: u64,
        #[command(flatten)]
        login: LoginFlags,
    },
    /// Print the owner's settings as JSON (admins), or replace them with
    /// a file's (`--set FILE.json`, as printed; the portal checks them).
    Settings {
        /// The settings to store, as `subsume lab settings` prints them.
        #[arg(long, value_name = "FILE.json")]
        set: Option<PathBuf>,
        #[command(flatten)]
        login: LoginFlags,
    },
    /// Download the lab kit (the lab's robot in its preflight form, its
    /// components, world and criteria) into a new or empty folder; then
    /// `subsume run DIR/robot.xml --http off --speed max --duration 60
    /// --criteria DIR/criteria.json` gives the verdict the lab's preflight
    /// would.
    Kit {
        /// The folder to unpack into.
        #[arg(short = 'o', long = "output", value_name = "DIR")]
        output: PathBuf,
        #[command(flatten)]
        login: LoginFlags,
    },
}

#[derive(clap::Args)]
struct ServeArgs {
    /// Where the lab's portal listens.
    #[arg(long, value_name = "ADDRESS", default_value = "127.0.0.1:8080")]
    http: std::net::SocketAddr,
    /// The lab's name (robots join it by this name).
    #[arg(long, value_name = "NAME", default_value = "lab")]
    lab: String,
    /// The lab's shared secret; made when missing [default:
    /// STORE/lab.secret]. Copy it to each robot.
    #[arg(long, value_name = "FILE")]
    secret: Option<PathBuf>,
    /// The Zenoh config (JSON5: TLS, user/password) of the lab's session.
    #[arg(long, value_name = "FILE")]
    zenoh_config: Option<PathBuf>,
    /// Zenoh endpoints to connect to, comma-separated.
    #[arg(long, value_name = "ENDPOINTS", default_value = "")]
    connect: String,
    /// Zenoh endpoints to listen on, comma-separated.
    #[arg(long, value_name = "ENDPOINTS", default_value = "")]
    listen: String,
    /// How long robots have to show their tokens after a start before the
    /// experiments they ran are marked lost (0 to 3600).
    #[arg(long, value_name = "SECONDS", default_value = "15",
          value_parser = |t: &str| super::flags::seconds_within(t, std::time::Duration::ZERO, std::time::Duration::from_secs(3600)))]
    relearn: std::time::Duration,
    /// How long the lab waits for a robot's answer to a dispatch (1 to
    /// 600). A robot that does not answer in time has the experiment
    /// withdrawn (it starts it only before this time, less a fifth) and
    /// it goes back to the queue.
    #[arg(long, value_name = "SECONDS", default_value = "150",
          value_parser = |t: &str| super::flags::seconds_within(t, subsume::lab::server::MIN_DISPATCH_TIMEOUT, subsume::lab::server::MAX_DISPATCH_TIMEOUT))]
    dispatch_timeout: std::time::Duration,
    /// The certificate chain (PEM) the portal serves TLS with.
    #[arg(long, value_name = "FILE", env = "SUBSUME_TLS_CERT")]
    tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert.
    #[arg(long, value_name = "FILE", env = "SUBSUME_TLS_KEY")]
    tls_key: Option<PathBuf>,
    /// Allow plain HTTP on addresses other than loopback.
    #[arg(long, env = "SUBSUME_ALLOW_PLAIN_HTTP")]
    allow_plain_http: bool,
    /// Allow the lab's Zenoh listener or connections off loopback in plain
    /// text, or over TLS that authenticates nobody (a closed network only).
    #[arg(long)]
    allow_plain_zenoh: bool,
    /// How the preflights run: `background` (nice 10, behind the lab's
    /// portal and dispatch), `idle` (only the CPU nothing else wants) or
    /// `normal` (a machine that does nothing else).
    #[arg(long, value_name = "idle|background|normal", default_value = "background")]
    preflight_priority: subsume::lab::preflight::Priority,
}

impl ServeArgs {
    fn execute(self, context: &super::Context) -> anyhow::Result<ExitCode> {
        use anyhow::Context as _;
        let store_dir = context.store_dir()?;
        std::fs::create_dir_all(&store_dir).with_context(|| format!("cannot make {}", store_dir.display()))?;
        let secret = self.secret.unwrap_or_else(|| store_dir.join("lab.secret"));
        let key = subsume::lab::wire::LabKey::from_file_or_new(&self.lab, &secret)?;
        let allow = (self.allow_plain_zenoh, "--allow-plain-zenoh");
        let session = super::flags::lab_session(self.zenoh_config, &self.connect, &self.listen, allow)?;
        let identity = subsume::tls::TlsIdentity::from_options(self.tls_cert.as_deref(), self.tls_key.as_deref())?;
        let options = subsume::run::LabServeOptions {
            listen: self.http,
            store_dir,
            logs: context.logs.clone(),
            cache_dir: context.cache_dir.clone(),
            tls: subsume::tls::HostTls { identity, allow_plain_remote: self.allow_plain_http },
            fleet: subsume::lab::server::FleetOptions {
                key,
                session,
                relearn: self.relearn,
                dispatch_timeout: self.dispatch_timeout,
            },
            preflight_priority: self.preflight_priority,
            // As `subsume run`: a first admin for a person at a terminal,
            // a hint for a service unit or a pipe.
            first_user: if std::io::IsTerminal::is_terminal(&std::io::stdout()) {
                subsume::run::FirstUser::MakeAdmin
            } else {
                subsume::run::FirstUser::Hint
            },
        };
        let shutdown = subsume::runtime::control_loop::Shutdown::new();
        let signals = crate::install_signal_handlers(shutdown.clone())?;
        let result = subsume::run::serve_lab(&options, shutdown);
        signals.close();
        result?;
        Ok(ExitCode::SUCCESS)
    }
}

#[derive(clap::Args)]
struct RouterConfigArgs {
    /// The lab's name (as `subsume lab serve --lab NAME`).
    #[arg(long, value_name = "NAME")]
    lab: String,
    /// A robot of the lab (as `subsume run ... --lab-robot NAME`), also its
    /// user's name on the router; once per robot.
    #[arg(long = "robot", value_name = "NAME")]
    robots: Vec<String>,
    /// The router's listen endpoint.
    #[arg(long, value_name = "ENDPOINT", default_value = router_config::DEFAULT_LISTEN)]
    listen: String,
    /// The router's users file (`user:password` per line).
    #[arg(long, value_name = "PATH", default_value = router_config::DEFAULT_USERS_FILE)]
    users_file: String,
    /// The lab server's user on the router.
    #[arg(long, value_name = "USER", default_value = router_config::DEFAULT_LAB_SERVER_USER)]
    lab_server_user: String,
    /// The router's certificate chain (PEM), for a tls/ listen endpoint;
    /// needs --tls-key.
    #[arg(long, value_name = "PATH")]
    tls_cert: Option<String>,
    /// The private key (PEM) of --tls-cert.
    #[arg(long, value_name = "PATH")]
    tls_key: Option<String>,
}

#[derive(clap::Args)]
struct SubmitArgs {
    /// A component of the robot and its file: uploaded under NAME
    /// (repeatable); the robot file's component NAME runs it.
    #[arg(long = "component", value_name = "NAME=FILE.wasm", value_parser = component_arg)]
    components: Vec<(String, PathBuf)>,
    /// The robot file of the experiment (read and parsed here first);
    /// without it, the robot file that runs now.
    #[arg(long, value_name = "FILE.xml")]
    robot: Option<PathBuf>,
    /// How long it runs on the robot, in seconds (at most the robot's
    /// max-duration).
    #[arg(long, value_name = "SECONDS")]
    duration: f64,
    /// A label shown with it.
    #[arg(long, value_name = "TEXT", default_value = "")]
    label: String,
    /// When it ends, download its results and unpack them into this new or
    /// empty folder.
    #[arg(long, value_name = "DIR")]
    results: Option<PathBuf>,
    /// The platform the uploads belong to.
    #[arg(long, default_value = "control")]
    platform: String,
    /// On a lab server: which robots may run it, `robot=NAME` or
    /// `profile=ID` (`subsume lab robots` lists both); the experiment
    /// builds on that robot's or profile's baseline. Any robot by default.
    #[arg(long, value_name = "robot=NAME|profile=ID", value_parser = target_arg)]
    target: Option<Target>,
    #[command(flatten)]
    login: LoginFlags,
}

/// A reservation's start: `+MINUTES` from `now_ms`, or an RFC 3339 time
/// (`2026-11-29T10:00:00Z`).
fn reservation_start(text: &str, now_ms: u64) -> anyhow::Result<u64> {
    if let Some(minutes) = text.strip_prefix('+') {
        let minutes: f64 = minutes
            .parse()
            .ok()
            .filter(|m: &f64| m.is_finite() && *m >= 0.0)
            .ok_or_else(|| anyhow::anyhow!("--start {text}: +MINUTES takes a number of minutes from now"))?;
        return Ok(now_ms.saturating_add((minutes * 60_000.0).round() as u64));
    }
    let at: jiff::Timestamp = text.parse().map_err(|e| {
        anyhow::anyhow!("--start {text}: neither +MINUTES nor a UTC time like 2026-11-29T10:00:00Z ({e})")
    })?;
    u64::try_from(at.as_millisecond()).map_err(|_| anyhow::anyhow!("--start {text}: before 1970"))
}

/// The client's login from the shared flags.
fn to_login(flags: LoginFlags) -> Login {
    flags.login()
}

fn print_json(value: &impl serde::Serialize) -> anyhow::Result<()> {
    println!("{}", serde_json::to_string_pretty(value)?);
    Ok(())
}

impl LabCommand {
    pub fn execute(self, context: &super::Context) -> anyhow::Result<ExitCode> {
        match self.action {
            LabAction::Serve(args) => args.execute(context),
            LabAction::RouterConfig(args) => {
                let options = RouterConfigOptions {
                    lab: args.lab,
                    robots: args.robots,
                    listen: args.listen,
                    users_file: args.users_file,
                    lab_server_user: args.lab_server_user,
                    tls_certificate: args.tls_cert,
                    tls_private_key: args.tls_key,
                };
                print!("{}", router_config::router_config(&options)?);
                Ok(ExitCode::SUCCESS)
            }
            LabAction::Submit(args) => {
                let request = SubmitRequest {
                    login: to_login(args.login),
                    platform: args.platform,
                    components: args.components,
                    robot: args.robot,
                    duration_s: args.duration,
                    label: args.label,
                    results: args.results,
                    target: args.target.unwrap_or_default(),
                };
                let mut progress = |line: &str| eprintln!("lab: {line}");
                let mut states = |line: &str| println!("{line}");
                let submitted =
                    lab_client::submit(&request, &mut Say { progress: &mut progress, states: &mut states })?;
                Ok(if submitted.experiment.record.state == ExperimentState::Done {
                    ExitCode::SUCCESS
                } else {
                    ExitCode::FAILURE
                })
            }
            LabAction::List { json, login } => {
                let experiments = lab_client::list(&to_login(login))?;
                if json {
                    print_json(&experiments)?;
                } else {
                    print!("{}", list_text(&experiments, now_ms()));
                }
                Ok(ExitCode::SUCCESS)
            }
            LabAction::Show { id, json, login } => {
                let experiment = lab_client::show(&to_login(login), id)?;
                if json {
                    print_json(&experiment)?;
                } else {
                    print!("{}", show_text(&experiment, now_ms()));
                }
                Ok(ExitCode::SUCCESS)
            }
            LabAction::Cancel { id, login } => {
                let record = lab_client::cancel(&to_login(login), id)?;
                let cause = record.history.last().map_or("", |c| c.cause.as_str());
                println!("experiment {id}: {}: {cause}", record.state);
                Ok(ExitCode::SUCCESS)
            }
            LabAction::Reserve { start, minutes, for_user, login } => {
                let now = now_ms();
                let start_ms = reservation_start(&start, now)?;
                if !(minutes.is_finite() && minutes > 0.0 && minutes <= 30.0 * 24.0 * 60.0) {
                    anyhow::bail!("--minutes must be more than 0 and at most 30 days' worth, got {minutes}");
                }
                let end_ms = start_ms.saturating_add((minutes * 60_000.0).round() as u64);
                let r = lab_client::reserve(&to_login(login), start_ms, end_ms, for_user.as_deref())?;
                println!("reservation {} for {}:", r.id, r.user);
                print!("{}", lab_client::reservations_text(std::slice::from_ref(&r), now));
                Ok(ExitCode::SUCCESS)
            }
            LabAction::Selftest { login } => {
                let test = lab_client::self_test(&to_login(login))?;
                for check in &test.checks {
                    let mark = if check.passed { "ok  " } else { "FAIL" };
                    println!("{mark} {}: {}", check.check, check.detail);
                }
                if test.passed {
                    println!("the self-test passed");
                    Ok(ExitCode::SUCCESS)
                } else {
                    println!("the self-test failed: the robot is out of service until an admin ends it");
                    Ok(ExitCode::from(1))
                }
            }
            LabAction::Maintenance { reason, end: _, login } => {
                let of = lab_client::maintenance(&to_login(login), reason.as_deref())?;
                match (&reason, of) {
                    (Some(reason), MaintenanceOf::Robot) => println!(
                        "the robot is in maintenance: {reason}; no experiment starts until `subsume lab maintenance --end`"
                    ),
                    (Some(reason), MaintenanceOf::Lab) => println!(
                        "the lab is in maintenance: {reason}; no experiment goes to any robot until `subsume lab maintenance --end` (a running one goes on)"
                    ),
                    (None, MaintenanceOf::Robot) => println!("the robot is back in service; the queue goes on"),
                    (None, MaintenanceOf::Lab) => println!("the lab is back in service; its queue goes to the robots"),
                }
                Ok(ExitCode::SUCCESS)
            }
            LabAction::Reservations { json, login } => {
                let reservations = lab_client::reservations(&to_login(login))?;
                if json {
                    print_json(&reservations)?;
                } else {
                    print!("{}", lab_client::reservations_text(&reservations, now_ms()));
                }
                Ok(ExitCode::SUCCESS)
            }
            LabAction::Unreserve { id, login } => {
                lab_client::unreserve(&to_login(login), id)?;
                println!("reservation {id} cancelled");
                Ok(ExitCode::SUCCESS)
            }
            LabAction::Settings { set, login } => {
                use anyhow::Context as _;
                let login = to_login(login);
                let settings = match set {
                    None => lab_client::settings(&login)?,
                    Some(file) => {
                        let text = std::fs::read(&file).with_context(|| format!("cannot read {}", file.display()))?;
                        let wanted: serde_json::Value = serde_json::from_slice(&text)
                            .with_context(|| format!("{}: not JSON; nothing was sent", file.display()))?;
                        lab_client::set_settings(&login, &wanted)?
                    }
                };
                print_json(&settings)?;
                Ok(ExitCode::SUCCESS)
            }
            LabAction::Results { id, output, login } => {
                let unpacked = lab_client::results(&to_login(login), id, &output)?;
                println!("{}", lab_client::unpacked_text(id, &unpacked));
                Ok(ExitCode::SUCCESS)
            }
            LabAction::Kit { output, login } => {
                let unpacked = lab_client::kit(&to_login(login), &output)?;
                let dir = unpacked.dir.display();
                println!("the lab kit: {dir} ({} files, sha256 checked)", unpacked.files);
                println!(
                    "try the lab's robot as its preflight does: subsume run {dir}/robot.xml --http off --speed max --duration 60 --criteria {dir}/criteria.json"
                );
                Ok(ExitCode::SUCCESS)
            }
        }
    }
}
