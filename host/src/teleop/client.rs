//! `subsume teleop HOST:PORT`: a keyboard teleoperation client in the
//! terminal. Arrow keys change speed and turn rate, space stops, `m` cycles
//! the requested control mode, `q` (or Esc, Ctrl-C) quits. It speaks the TCP
//! line protocol of docs/teleop.md, answers pings at once, sends the current
//! command ten times a second while a mode is granted, and shows the granted
//! mode and the measured round-trip time. With `--tls-ca` it speaks TLS,
//! checking the host's certificate against that CA.

use std::io::Write;
use std::path::PathBuf;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use crossterm::event::{self, Event, KeyCode, KeyEvent, KeyEventKind, KeyModifiers};
use crossterm::terminal;

use crate::teleop::mode::Mode;

/// Commands per second while a mode is granted.
pub const SEND_RATE_HZ: u64 = 10;
/// Speed change per arrow key press, m/s and rad/s.
pub const LINEAR_STEP: f64 = 0.05;
pub const ANGULAR_STEP: f64 = 0.2;
/// Fastest speeds the client asks for.
pub const MAX_LINEAR: f64 = 1.0;
pub const MAX_ANGULAR: f64 = 2.0;

#[derive(Clone, Debug)]
pub struct ClientOptions {
    pub address: String,
    pub name: String,
    pub token: String,
    /// Speak TLS, trusting this CA (PEM) for the host's certificate.
    pub tls_ca: Option<PathBuf>,
}

/// What the screen shows.
#[derive(Debug, Default)]
struct View {
    granted: Option<Mode>,
    requested: Option<Mode>,
    rtt: Option<String>,
    allowed: Vec<Mode>,
    linear: f64,
    angular: f64,
    last: String,
    /// Whether our commands drive the robot, from the host's CONTROL lines.
    control: Option<String>,
}

/// Why the keyboard client stopped with an error.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct ClientError(String);

/// Runs the client until the operator quits or the host closes.
pub fn run(options: &ClientOptions) -> Result<(), ClientError> {
    session(options).map_err(ClientError)
}

/// A connection to the host: plain TCP or TLS.
trait Connection: tokio::io::AsyncRead + tokio::io::AsyncWrite + Send + Unpin {}
impl<T: tokio::io::AsyncRead + tokio::io::AsyncWrite + Send + Unpin> Connection for T {}

/// Connects to the host, over TLS when `tls_ca` names the CA to trust.
async fn connect(options: &ClientOptions) -> Result<Box<dyn Connection>, String> {
    let tcp = tokio::net::TcpStream::connect(&options.address)
        .await
        .map_err(|e| format!("cannot connect to {}: {e}", options.address))?;
    let _ = tcp.set_nodelay(true);
    let Some(ca) = &options.tls_ca else { return Ok(Box::new(tcp)) };
    let config = crate::tls::client_config(ca).map_err(|e| e.to_string())?;
    let host = options.address.rsplit_once(':').map_or(options.address.as_str(), |(host, _)| host);
    let host = host.trim_start_matches('[').trim_end_matches(']');
    let name = tokio_rustls::rustls::pki_types::ServerName::try_from(host.to_string())
        .map_err(|e| format!("'{host}' is not a host name or address for TLS: {e}"))?;
    tokio_rustls::TlsConnector::from(config)
        .connect(name, tcp)
        .await
        .map(|stream| Box::new(stream) as Box<dyn Connection>)
        .map_err(|e| format!("TLS with {} failed: {e}", options.address))
}

fn session(options: &ClientOptions) -> Result<(), String> {
    use tokio::io::{AsyncBufReadExt as _, AsyncWriteExt as _};
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| format!("cannot start the network thread: {e}"))?;
    let stream = runtime.block_on(connect(options))?;
    // One thread does the network I/O (reads and writes at once, TLS or
    // not); the terminal loop talks to it through channels.
    let (lines_tx, lines) = mpsc::channel::<String>();
    let (out_tx, mut out_rx) = tokio::sync::mpsc::unbounded_channel::<String>();
    let io = std::thread::spawn(move || {
        runtime.block_on(async move {
            let (read, mut write) = tokio::io::split(stream);
            let mut reader = tokio::io::BufReader::new(read).lines();
            loop {
                tokio::select! {
                    line = reader.next_line() => match line {
                        Ok(Some(line)) => if lines_tx.send(line).is_err() { break },
                        _ => break,
                    },
                    out = out_rx.recv() => match out {
                        Some(text) => if write.write_all(text.as_bytes()).await.is_err() { break },
                        None => {
                            let _ = write.shutdown().await;
                            break;
                        }
                    },
                }
            }
        });
    });
    let send = |line: &str| out_tx.send(format!("{line}\n")).map_err(|_| "the host closed the connection".to_string());
    send(&format!("AUTH {} {}", options.name, options.token))?;

    terminal::enable_raw_mode().map_err(|e| format!("cannot use the terminal: {e}"))?;
    let result = event_loop(&lines, &mut |line: &str| send(line));
    let _ = terminal::disable_raw_mode();
    println!();
    // What was sent last (QUIT) goes out before the process ends.
    drop(out_tx);
    let _ = io.join();
    result
}

fn event_loop(lines: &mpsc::Receiver<String>, send: &mut dyn FnMut(&str) -> Result<(), String>) -> Result<(), String> {
    let mut view = View { last: "connecting".into(), ..View::default() };
    let started = Instant::now();
    let mut seq = 0u64;
    let mut next_send = Instant::now();
    loop {
        // Host lines first: pings must be answered at once.
        loop {
            match lines.try_recv() {
                Ok(line) => {
                    if let Some(reply) = handle_line(&line, &mut view) {
                        send(&reply)?;
                    }
                }
                Err(mpsc::TryRecvError::Empty) => break,
                Err(mpsc::TryRecvError::Disconnected) => {
                    return Err(format!("the host closed the connection ({})", view.last));
                }
            }
        }
        if event::poll(Duration::from_millis(5)).map_err(|e| e.to_string())?
            && let Event::Key(key) = event::read().map_err(|e| e.to_string())?
        {
            match handle_key(key, &mut view) {
                KeyAction::Quit => {
                    let _ = send("QUIT");
                    return Ok(());
                }
                KeyAction::Send(line) => send(&line)?,
                KeyAction::None => {}
            }
        }
        if view.granted.is_some() && Instant::now() >= next_send {
            next_send = Instant::now() + Duration::from_millis(1000 / SEND_RATE_HZ);
            seq += 1;
            let command = if view.linear == 0.0 && view.angular == 0.0 {
                "STOP".to_string()
            } else {
                format!("VEL {:.2} {:.2}", view.linear, view.angular)
            };
            send(&format!("CMD {seq} {} {command}", started.elapsed().as_millis()))?;
        }
        draw(&view);
    }
}

enum KeyAction {
    None,
    Quit,
    Send(String),
}

fn handle_key(key: KeyEvent, view: &mut View) -> KeyAction {
    if key.kind == KeyEventKind::Release {
        return KeyAction::None;
    }
    match key.code {
        KeyCode::Char('q') | KeyCode::Esc => return KeyAction::Quit,
        KeyCode::Char('c') if key.modifiers.contains(KeyModifiers::CONTROL) => return KeyAction::Quit,
        KeyCode::Up => view.linear = (view.linear + LINEAR_STEP).min(MAX_LINEAR),
        KeyCode::Down => view.linear = (view.linear - LINEAR_STEP).max(-MAX_LINEAR),
        KeyCode::Left => view.angular = (view.angular + ANGULAR_STEP).min(MAX_ANGULAR),
        KeyCode::Right => view.angular = (view.angular - ANGULAR_STEP).max(-MAX_ANGULAR),
        KeyCode::Char(' ') => {
            view.linear = 0.0;
            view.angular = 0.0;
        }
        KeyCode::Char('m') => {
            let next = match view.requested.or(view.granted) {
                Some(Mode::Direct) => Mode::Shared,
                Some(Mode::Shared) => Mode::Supervisory,
                Some(Mode::Supervisory) | None => Mode::Direct,
            };
            view.requested = Some(next);
            return KeyAction::Send(format!("MODE {next}"));
        }
        _ => {}
    }
    // Snap tiny float residues to zero so "stopped" really is.
    if view.linear.abs() < 1e-9 {
        view.linear = 0.0;
    }
    if view.angular.abs() < 1e-9 {
        view.angular = 0.0;
    }
    KeyAction::None
}

/// Updates the view from a host line; returns a line to send back.
fn handle_line(line: &str, view: &mut View) -> Option<String> {
    let mut words = line.split_ascii_whitespace();
    match words.next() {
        Some("PING") => return words.next().map(|nonce| format!("PONG {nonce}")),
        Some("RTT") => {
            let rtt = words.next().unwrap_or("?");
            let jitter = words.nth(1).unwrap_or("?");
            view.rtt = Some(format!("{rtt} ms (jitter {jitter} ms)"));
            view.allowed = words.nth(1).unwrap_or("").split(',').filter_map(Mode::parse).collect();
            if view.granted.is_none() && view.requested.is_none() {
                // Ask for the best mode the link allows.
                let best = view.allowed.first().copied().unwrap_or(Mode::Supervisory);
                view.requested = Some(best);
                return Some(format!("MODE {best}"));
            }
        }
        Some("CONTROL") => {
            view.control = match (words.next(), words.next()) {
                (Some("held"), _) => Some("you drive".into()),
                (Some("suppressed"), Some(holder)) => Some(format!("{holder} drives")),
                (Some("idle"), _) => Some("idle".into()),
                _ => None,
            };
            view.last = line.split_once(' ').map_or(line, |(_, rest)| rest).to_string();
        }
        Some("MODE") => {
            view.granted = words.next().and_then(Mode::parse);
            view.requested = None;
            view.last = line.to_string();
        }
        _ => view.last = line.to_string(),
    }
    None
}

fn draw(view: &View) {
    let mode = view.granted.map_or("none".to_string(), |m| m.to_string());
    let status = format!(
        "\r\x1b[2Kmode {mode} | {} | rtt {} | vel {:+.2} m/s turn {:+.2} rad/s | arrows, space, m, q | {}",
        view.control.as_deref().unwrap_or("idle"),
        view.rtt.as_deref().unwrap_or("?"),
        view.linear,
        view.angular,
        view.last.chars().take(60).collect::<String>()
    );
    let mut out = std::io::stdout();
    let _ = out.write_all(status.as_bytes());
    let _ = out.flush();
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(code: KeyCode) -> KeyEvent {
        KeyEvent::new(code, KeyModifiers::NONE)
    }

    #[test]
    fn keys_change_speed_stop_and_cycle_modes() {
        let mut view = View::default();
        for code in [KeyCode::Up, KeyCode::Up, KeyCode::Left] {
            handle_key(key(code), &mut view);
        }
        assert!((view.linear - 0.1).abs() < 1e-9 && (view.angular - 0.2).abs() < 1e-9);
        handle_key(key(KeyCode::Char(' ')), &mut view);
        assert_eq!((view.linear, view.angular), (0.0, 0.0));
        let modes: Vec<String> = (0..4)
            .filter_map(|_| match handle_key(key(KeyCode::Char('m')), &mut view) {
                KeyAction::Send(line) => Some(line),
                _ => None,
            })
            .collect();
        assert_eq!(modes, ["MODE direct", "MODE shared", "MODE supervisory", "MODE direct"]);
        assert!(matches!(handle_key(key(KeyCode::Char('q')), &mut view), KeyAction::Quit));
    }

    #[test]
    fn host_lines_update_the_view_and_pings_are_answered() {
        let mut view = View::default();
        assert_eq!(handle_line("PING 7", &mut view), Some("PONG 7".into()));
        assert_eq!(
            handle_line("RTT 12.5 JITTER 0.3 ALLOWED shared,supervisory", &mut view),
            Some("MODE shared".into())
        );
        assert_eq!(view.rtt.as_deref(), Some("12.5 ms (jitter 0.3 ms)"));
        assert_eq!(handle_line("MODE shared granted: rtt 12.5 ms", &mut view), None);
        assert_eq!(view.granted, Some(Mode::Shared));
        handle_line(
            "CONTROL suppressed avoid 3 suppressed by avoid (priority 3): no control mode outranks it",
            &mut view,
        );
        assert_eq!(view.control.as_deref(), Some("avoid drives"));
        handle_line("CONTROL held your commands drive the robot", &mut view);
        assert_eq!(view.control.as_deref(), Some("you drive"));
    }
}
