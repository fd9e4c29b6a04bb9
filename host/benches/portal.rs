//! Upload -> active through the portal's router, in process, with the demo
//! robot running on its control loop: upload a component (never seen
//! before: a custom section makes each upload new, so it is compiled),
//! upload a robot file naming it, activate it. For a Rust component and a
//! large one (the Python avoider by default, `SUBSUME_LARGE_COMPONENT` to
//! choose). While the large one compiles, the 100 Hz serial link's tick rate
//! is read from the live status: the control loop must keep it.
//!
//! `cargo bench --bench portal`

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::Request;
use subsume::builtin::Services;
use subsume::deploy::{BootOptions, Deployer};
use subsume::portal::{self, PortalState};
use subsume::runtime::control_loop::{self, Clock, Shutdown};
use subsume::sandbox::Sandbox;
use subsume::store::Store;
use subsume::store::users::{Directory, Role};
use subsume::teleop::TeleopServers;
use tower::ServiceExt as _;

const ROUNDS: usize = 10;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// `bytes` with a custom section appended: a different component to every
/// cache, the same behaviour.
fn unique(bytes: &[u8], round: usize) -> Vec<u8> {
    let name = b"bench";
    let payload = format!("round {round} {:?}", Instant::now());
    let content_len = 1 + name.len() + payload.len();
    let mut out = bytes.to_vec();
    out.push(0); // custom section
    out.push(content_len as u8); // < 128: one LEB128 byte
    out.push(name.len() as u8);
    out.extend_from_slice(name);
    out.extend_from_slice(payload.as_bytes());
    out
}

async fn call(app: &axum::Router, token: &str, method: &str, uri: &str, body: Vec<u8>) -> (u16, serde_json::Value) {
    let request = Request::builder()
        .method(method)
        .uri(uri)
        .header("authorization", format!("Bearer {token}"))
        .body(Body::from(body))
        .map_err(|e| e.to_string());
    let Ok(request) = request else { return (0, serde_json::Value::Null) };
    let response = match app.clone().oneshot(request).await {
        Ok(response) => response,
        Err(never) => match never {},
    };
    let status = response.status().as_u16();
    let bytes = axum::body::to_bytes(response.into_body(), usize::MAX).await.unwrap_or_default();
    (status, serde_json::from_slice(&bytes).unwrap_or_default())
}

async fn upload(app: &axum::Router, token: &str, wasm: Vec<u8>, name: &str) -> Result<(), String> {
    let (status, json) = call(app, token, "PUT", &format!("/api/v1/platforms/control/components/{name}"), wasm).await;
    if status == 201 { Ok(()) } else { Err(format!("upload: {status} {json}")) }
}

/// Stages the demo with component `name` as its avoider, and activates it.
async fn stage_and_activate(app: &axum::Router, token: &str, name: &str) -> Result<(), String> {
    let demo = std::fs::read_to_string(repo().join("config/demo.xml")).map_err(|e| e.to_string())?;
    let robot =
        demo.replace("../guest-components/rust/target/wasm32-wasip2/release/avoider.wasm", &format!("{name}.wasm"));
    let (status, json) =
        call(app, token, "PUT", &format!("/api/v1/platforms/control/configs/{name}.xml"), robot.into_bytes()).await;
    if status != 201 {
        return Err(format!("stage: {status} {json}"));
    }
    let id = json["set"]["id"].as_u64().unwrap_or(0);
    let (status, json) = call(app, token, "POST", &format!("/api/v1/sets/{id}/activate"), Vec::new()).await;
    if status != 200 {
        return Err(format!("activate: {status} {json}"));
    }
    Ok(())
}

/// Upload, stage and activate `wasm` as the demo's avoider; returns the time.
async fn upload_to_active(app: &axum::Router, token: &str, wasm: Vec<u8>, name: &str) -> Result<Duration, String> {
    let start = Instant::now();
    upload(app, token, wasm, name).await?;
    stage_and_activate(app, token, name).await?;
    Ok(start.elapsed())
}

fn ticks_of(status: &serde_json::Value, component: &str) -> (f64, f64) {
    let c = status["components"].as_array().and_then(|cs| cs.iter().find(|c| c["name"] == component).cloned());
    let c = c.unwrap_or_default();
    (c["ticks"].as_f64().unwrap_or(0.0), c["missed_ticks"].as_f64().unwrap_or(0.0))
}

fn main() -> Result<(), String> {
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let store = Arc::new(Store::open(&dir.path().join("store")).map_err(|e| e.to_string())?);
    store
        .lock()
        .and_then(|w| Ok(w.users_mut().add("bench", Role::Admin, &[], "bench-password-1", false)?))
        .map_err(|e| e.to_string())?;
    let directory = Arc::new(Directory::new(store.users().clone()));
    let shutdown = Shutdown::new();
    let clock = Clock::new();
    let overrides = ["teleop.listen=127.0.0.1:0", "teleop.websocket="]
        .iter()
        .map(|o| o.parse())
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e: subsume::config::BadOverride| e.to_string())?;
    let boot = Deployer::boot(BootOptions {
        store,
        sandbox: Arc::new(Sandbox::new(Some(dir.path().join("cache"))).map_err(|e| e.to_string())?),
        services: Services::default().with(directory.clone()).with(Arc::new(TeleopServers::default())),
        config_path: &repo().join("config/demo.xml"),
        overrides,
        clock: clock.clone(),
        waker: shutdown.waker(),
    })
    .map_err(|e| e.to_string())?;
    let subsume::deploy::Boot { deployer, mut graph, mut hook } = boot;
    let loop_shutdown = shutdown.clone();
    let control =
        std::thread::spawn(move || control_loop::run_with(&mut graph, &clock, &loop_shutdown, None, &mut hook));
    let mut live = deployer.live().subscribe();
    let lab = subsume::lab::Lab::start(
        deployer.clone(),
        subsume::lab::LabOptions {
            preflight: subsume::lab::preflight::PreflightCommand {
                exe: std::path::PathBuf::from(env!("CARGO_BIN_EXE_subsume")),
                cache_dir: None,
                priority: subsume::lab::preflight::Priority::Idle,
                limits: subsume::lab::preflight::PreflightLimits::default(),
            },
            role: subsume::lab::LabRole::Alone,
        },
    )
    .map_err(|e| e.to_string())?;
    let app = portal::app(PortalState::new(deployer, lab, directory, portal::logs::LogRing::new()));
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .map_err(|e| e.to_string())?;
    rt.block_on(async {
        let login = serde_json::json!({ "name": "bench", "password": "bench-password-1" }).to_string();
        let request = Request::post("/api/v1/login").body(Body::from(login)).map_err(|e| e.to_string())?;
        let response = match app.clone().oneshot(request).await {
            Ok(response) => response,
            Err(never) => match never {},
        };
        let bytes = axum::body::to_bytes(response.into_body(), usize::MAX).await.map_err(|e| e.to_string())?;
        let token = serde_json::from_slice::<serde_json::Value>(&bytes).map_err(|e| e.to_string())?["token"]
            .as_str()
            .unwrap_or_default()
            .to_string();

        let rust = std::fs::read(repo().join("guest-components/rust/target/wasm32-wasip2/release/avoider.wasm"))
            .map_err(|e| format!("build the guests first (scripts/setup): {e}"))?;
        let mut times = Vec::new();
        for round in 0..ROUNDS {
            times.push(upload_to_active(&app, &token, unique(&rust, round), &format!("rust-{round}")).await?);
        }
        times.sort();
        println!(
            "rust avoider ({} KiB): upload -> active p50 {:.1} ms, min {:.1} ms, max {:.1} ms ({ROUNDS} rounds, each compiled)",
            rust.len() / 1024,
            times[ROUNDS / 2].as_secs_f64() * 1e3,
            times[0].as_secs_f64() * 1e3,
            times[ROUNDS - 1].as_secs_f64() * 1e3
        );

        let large_path = std::env::var_os("SUBSUME_LARGE_COMPONENT")
            .map(PathBuf::from)
            .unwrap_or_else(|| repo().join("guest-components/python/avoider/avoider.wasm"));
        match std::fs::read(&large_path) {
            Ok(large) => {
                let _ = live.borrow_and_update();
                let _ = live.changed().await;
                let before = serde_json::to_value(&*live.borrow_and_update().clone()).unwrap_or_default();
                let start = Instant::now();
                upload(&app, &token, unique(&large, 0), "large").await?;
                let compiled = start.elapsed();
                let _ = live.changed().await;
                let after = serde_json::to_value(&*live.borrow_and_update().clone()).unwrap_or_default();
                stage_and_activate(&app, &token, "large").await?;
                let took = start.elapsed();
                let (t0, m0) = ticks_of(&before, "motors");
                let (t1, m1) = ticks_of(&after, "motors");
                let seconds = after["duration_s"].as_f64().unwrap_or(0.0) - before["duration_s"].as_f64().unwrap_or(0.0);
                println!(
                    "large component {} ({:.1} MiB): upload (compile) {:.2} s, upload -> active {:.2} s; while it compiled the 100 Hz serial link ticked {:.1} times/s ({} missed)",
                    large_path.display(),
                    large.len() as f64 / (1 << 20) as f64,
                    compiled.as_secs_f64(),
                    took.as_secs_f64(),
                    (t1 - t0) / seconds.max(1e-9),
                    m1 - m0
                );
            }
            Err(e) => println!("large component {}: not measured ({e}); build it with guest-components/build-all", large_path.display()),
        }
        Ok::<(), String>(())
    })?;
    shutdown.request();
    let _ = control.join();
    Ok(())
}
