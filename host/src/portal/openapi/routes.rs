//! The table of the API's operations: per operation its method, path,
//! summary, permission line, parameters, request body and answers, each
//! body a Rust type (`mod.rs` makes the document of it). A new route is a
//! row here; a new field is a field of its type.

use schemars::{Schema, SchemaGenerator};
use serde_json::{Value, json};

use super::{Content, Operation, Param, any_object, bytes, envelope, of, text, typed};
use crate::deploy::{
    Engaged, HistorySample, LocksView, ParamOverride, RecordingInfo, RecordingsView, Released, ReplayReport, SimStatus,
    SimView, Stopped, Validated,
};
use crate::lab::leaderboard::Board;
use crate::lab::server::RobotView;
use crate::lab::{ExperimentView, LabView, MailSubscription, RobotStop, Submission};
use crate::portal::auth::{LoginRequest, SessionUser};
use crate::portal::lab::{BaselineRequest, BookingRequest, MaintenanceRequest};
use crate::portal::logs::LogLine;
use crate::portal::routes::{ComponentView, ReplayRequest, SetStatus, StartRecording, VisibilityBody};
use crate::report::LiveStatus;
use crate::store::experiments::{ExperimentRecord, LabSettings, Maintenance, Reservation, SelfTest};
use crate::store::{AuditEntry, SetRecord, WiringGraph, WorldRecord};

/// Every operation of the API, a robot's and a lab server's (the table
/// tests/all/labserver_router.rs keeps says which serves which).
#[rustfmt::skip]
pub(super) fn operations() -> Vec<Operation> {
    vec![
        Operation::new("POST", "/api/v1/login", "Log in: returns a token (Bearer) and sets the session cookie", "none")
            .anyone()
            .body(typed::<LoginRequest>(), true)
            .ok(200, "logged in", Some(envelope([("token", of::<String>), ("user", of::<SessionUser>)])))
            .error(400, "malformed request")
            .error(401, "wrong user name or password")
            .error(429, "too many failed logins (Retry-After)")
            .error(503, "too many live sessions; try again later"),
        Operation::new("POST", "/api/v1/logout", "End the session", "any user")
            .ok(204, "logged out", None)
            .error(401, "not logged in"),
        Operation::new("GET", "/api/v1/session", "The logged-in user: name, role, platforms, may_drive", "any user")
            .ok(200, "the user", Some(typed::<SessionUser>()))
            .error(401, "not logged in"),
        Operation::new("GET", "/api/v1/components", "Stored components of every user with their declared ports and parameters; each has its owner (uploaded_by) and the source a robot file names it by (OWNER/NAME.wasm)", "any user")
            .ok(200, "the components", Some(envelope([("components", of::<Vec<ComponentView>>)])))
            .error(401, "not logged in"),
        Operation::new("GET", "/api/v1/components/{name}", "Your own stored component NAME (a robot file you stage names it NAME.wasm)", "any user")
            .param(Param::path("name", "upload name"))
            .ok(200, "the component", Some(typed::<ComponentView>()))
            .error(400, "a path parameter that is not UTF-8 once decoded")
            .error(401, "not logged in")
            .error(404, "no such component"),
        Operation::new("GET", "/api/v1/components/{owner}/{name}", "User OWNER's stored component NAME, if the caller may see it (its owner, an admin, anyone when it is shared with the lab, and non-researchers for the robot's own people's uploads; docs/portal.md, \"Who sees what\")", "any user; someone else's private upload answers 404 as a missing one")
            .param(Param::path("owner", "the user who uploaded it"))
            .param(Param::path("name", "upload name"))
            .ok(200, "the component", Some(typed::<ComponentView>()))
            .error(400, "a path parameter that is not UTF-8 once decoded")
            .error(401, "not logged in")
            .error(404, "no such component"),
        Operation::new("PUT", "/api/v1/components/{owner}/{name}/visibility", "Shares upload OWNER/NAME with the lab (visibility lab: every user may see it and run it as OWNER/NAME.wasm, read-only) or makes it private again", "its owner, or an admin; anyone else gets 404 as for a missing upload. Audited (component-visibility).")
            .param(Param::path("owner", "the user who uploaded it"))
            .param(Param::path("name", "upload name"))
            .body(typed::<VisibilityBody>(), true)
            .example(json!({"visibility": "lab"}))
            .ok(200, "the component, with its new visibility", Some(typed::<ComponentView>()))
            .error(400, "a body that is not {\"visibility\": \"private\" or \"lab\"}")
            .error(401, "not logged in")
            .error(404, "no such component, or not the caller's"),
        Operation::new("PUT", "/api/v1/platforms/{platform}/components/{name}", "Upload a .wasm component (the raw bytes as the body); checked against the component or translator world with the real linker, then stored by content as yours: it replaces your earlier upload of NAME, never another user's", "developer of the platform, admin")
            .param(Param::path("platform", "network or control").one_of(&["network", "control"]))
            .param(Param::path("name", "name your robot files' source attribute uses (NAME.wasm; OWNER/NAME.wasm from anyone's)"))
            .body(bytes("application/wasm"), true)
            .ok(201, "stored", Some(typed::<ComponentView>()))
            .error(400, "empty upload or bad name")
            .error(401, "not logged in")
            .error(403, "no permission for the platform")
            .error(404, "unknown platform")
            .error(409, "you keep the most components a user may; upload one of their names again to replace it")
            .error(413, "larger than the upload limit")
            .error(415, "not a webassembly component (core module, precompiled artifact, garbage)")
            .error(422, "a component of neither world")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("PUT", "/api/v1/platforms/{platform}/configs/{file}", "Upload a robot file (XML body); validated like `subsume check` against the stored components and staged as a new set (not active)", "developer of every platform the file changes, admin")
            .param(Param::path("platform", "network or control").one_of(&["network", "control"]))
            .param(Param::path("file", "plain file name, names the diagnostics"))
            .body(text("application/xml"), true)
            .ok(201, "staged", Some(envelope([("set", of::<SetRecord>)])))
            .error(400, "bad file name, not utf-8")
            .error(401, "not logged in")
            .error(403, "changes a platform the user may not change")
            .error(404, "unknown platform")
            .error(413, "larger than the robot-file limit")
            .error(422, "the file has errors (diagnostics with file:line:column)")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("POST", "/api/v1/platforms/{platform}/validate/{file}", "Validate a robot file (XML body) exactly as staging would, and store nothing (the portal editor's validate-as-you-type)", "as staging (developer of the platform, admin). One validation at a time: another meanwhile answers 429 with Retry-After")
            .param(Param::path("platform", "network or control").one_of(&["network", "control"]))
            .param(Param::path("file", "plain file name, names the diagnostics"))
            .body(text("application/xml"), true)
            .ok(200, "valid: components, connections, changes (platforms) and the wiring graph it would stage", Some(typed::<Validated>()))
            .error(400, "bad file name, not utf-8")
            .error(401, "not logged in")
            .error(403, "changes a platform the user may not change")
            .error(404, "unknown platform")
            .error(413, "larger than the robot-file limit")
            .error(422, "the file has errors (diagnostics with file, line, column, message)")
            .error(429, "another validation is running; try again"),
        Operation::new("GET", "/api/v1/worlds", "The uploaded simulator world files", "any logged-in user")
            .ok(200, "{\"worlds\": [{name, sha256, size, uploaded_by, uploaded_at}]}", Some(envelope([("worlds", of::<Vec<WorldRecord>>)])))
            .error(401, "not logged in"),
        Operation::new("PUT", "/api/v1/worlds/{file}", "Upload a simulator world file (text body), checked statement by statement; a robot file staged later names it in its simulator's `world` parameter, and the set pins its bytes", "developer of the control platform, admin")
            .param(Param::path("file", "plain file name ending with .world, as robot files name it"))
            .body(text("text/plain"), true)
            .ok(201, "stored", Some(envelope([("world", of::<WorldRecord>)])))
            .error(400, "bad file name (must end with .world), not utf-8, too large")
            .error(401, "not logged in")
            .error(403, "may not change the control platform")
            .error(413, "larger than the world-file limit")
            .error(422, "the file has errors (diagnostics with file:line:column)")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("GET", "/api/v1/sets", "Every set, newest first, with its status (active, previous, staged)", "any user; the list holds the baseline and the sets the caller may see (docs/portal.md, \"Who sees what\")")
            .ok(200, "the sets", Some(envelope([("active", of::<Option<u64>>), ("previous", of::<Option<u64>>), ("sets", listed_sets)])))
            .error(401, "not logged in"),
        Operation::new("GET", "/api/v1/sets/{id}", "One set: record, robot file, wiring graph", "any user may see the baseline and the sets they may see (docs/portal.md, \"Who sees what\"); someone else's set answers 404 as a missing one. `config` is null when the caller may not read the robot file. The answer's `overrides` lists the parameters `subsume run --param` sets on every set (component, param, value).")
            .param(Param::path("id", "set id").integer(false))
            .ok(200, "the set", Some(envelope([("config", of::<Option<String>>), ("graph", of::<WiringGraph>), ("overrides", of::<Vec<ParamOverride>>), ("set", of::<SetRecord>), ("status", of::<SetStatus>)])))
            .field_doc("config", "the robot file as staged; null when the caller may not read it (a researcher, for the robot's own robot file while the owner's lab kit is off)")
            .error(400, "the set id is not a whole number")
            .error(401, "not logged in")
            .error(404, "no such set"),
        Operation::new("DELETE", "/api/v1/sets/{id}", "Forgets set ID, staged by the caller (an admin: anyone's), that nothing needs: what a refused submission or activation left behind", "its stager, or an admin; someone else's set answers 404 as a missing one. Refused (409) while the set is active, in the rollback history, a baseline or an unfinished experiment's. Audited (forget-set).")
            .param(Param::path("id", "set id").integer(false))
            .ok(204, "forgotten", None)
            .error(400, "an id that is not a number")
            .error(401, "not logged in")
            .error(404, "no such set, or not the caller's")
            .error(409, "something needs the set"),
        Operation::new("POST", "/api/v1/sets/{id}/activate", "Build the set beside the running one and swap it in at a cycle boundary; on any error the running set is untouched", "developer of every platform the set changes, admin")
            .param(Param::path("id", "set id").integer(false))
            .ok(200, "{active, note}: note says what an admin's activation did first (it ends a running experiment and pauses the lab's queue), else null", Some(envelope([("active", of::<SetRecord>), ("note", of::<Option<String>>)])))
            .error(400, "the set id is not a whole number")
            .error(401, "not logged in")
            .error(403, "no permission")
            .error(404, "no such set")
            .error(409, "already active, or an experiment runs (developers; the answer names it and when it ends)")
            .error(422, "did not validate or start (errors)")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("POST", "/api/v1/sets/{id}/replay", "Replay the set's WASM components against a stored recording before activating it, comparing call by call: identical, or the first divergence of each port (the recorded call's time, number and kind, the port, what that call emitted on it in the recording and in the replay, how many calls differ)", "developer, admin. Body {\"recording\": NAME, \"only\": [COMPONENT...]} (only: optional, every WASM component when empty). One replay at a time; runs off the control loop and never touches the running set")
            .param(Param::path("id", "set id").integer(false))
            .body(typed::<ReplayRequest>(), true)
            .ok(200, "the replay report: {set, identical, report}", Some(envelope([("identical", of::<bool>), ("report", of::<ReplayReport>), ("set", of::<u64>)])))
            .error(400, "malformed body, not a recording name, or a component the set lacks or a built-in")
            .error(401, "not logged in")
            .error(403, "no permission")
            .error(404, "no such set or recording")
            .error(422, "the recording is not of this robot (calls or input ports missing), not an MCAP file, too large, or the replay took too long")
            .error(429, "another replay is running (Retry-After)"),
        Operation::new("POST", "/api/v1/rollback", "Activate the set that was active before the current one", "developer of every platform it changes, admin")
            .ok(200, "{active, note}: rolled back; note as for an activation", Some(envelope([("active", of::<SetRecord>), ("note", of::<Option<String>>)])))
            .error(401, "not logged in")
            .error(403, "no permission")
            .error(409, "nothing to roll back to, or an experiment runs (developers; the answer names it and when it ends)")
            .error(422, "did not start")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("GET", "/api/v1/status", "The live status: the run report's layout while running (components, arbiter, network, sim)", "any user")
            .ok(200, "the status", Some(typed::<Option<LiveStatus>>()))
            .error(401, "not logged in"),
        Operation::new("GET", "/api/v1/history", "The plots' history kept on the host: a sample of the live status a second (round-trip time per operator, messages out per second per component, the arbiter's holder), the last 300 (HISTORY_SAMPLES); the page draws it when it opens", "any user")
            .ok(200, "{period_s, max_samples, now_s (graph time), samples: [{t_s, set, rtt_ms: {OPERATOR: ms}, rates: {COMPONENT: per s}, holder}]}", Some(envelope([("max_samples", of::<usize>), ("now_s", of::<f64>), ("period_s", of::<f64>), ("samples", of::<Vec<HistorySample>>)])))
            .error(401, "not logged in"),
        Operation::new("GET", "/api/v1/events", "Server-sent events: `status` (live status, 5 Hz) and `log` (log lines)", "any user")
            .ok(200, "text/event-stream", Some(text("text/event-stream")))
            .error(401, "not logged in"),
        Operation::new("GET", "/api/v1/world", "The simulated world of the active set: bounds, obstacles, start, goal, rays", "any user")
            .ok(200, "the world", Some(typed::<SimView>()))
            .error(401, "not logged in")
            .error(404, "no simulated robot"),
        Operation::new("GET", "/api/v1/cameras", "The running cameras (builtin:camera components), for whoever may watch them", "the owner (admin) and operators; a researcher only while her own experiment runs on the robot")
            .ok(200, "{cameras: [name, ...]}", Some(envelope([("cameras", of::<Vec<String>>)])))
            .error(401, "not logged in")
            .error(403, "this user may not watch the cameras now"),
        Operation::new("GET", "/api/v1/cameras/{name}/live", "A camera live: its newest frames as an MJPEG stream (multipart/x-mixed-replace, each part a JPEG file), until the camera stops or the watcher may no longer watch", "the owner (admin) and operators; a researcher only while her own experiment runs on the robot")
            .param(Param::bare("name"))
            .ok(200, "multipart/x-mixed-replace; boundary=subsume-frame: one image/jpeg part per frame, with X-Capture-Ns (the loop's clock) and X-Seq", Some(text("multipart/x-mixed-replace")))
            .error(401, "not logged in")
            .error(403, "this user may not watch the cameras now")
            .error(404, "no such camera runs on this robot"),
        Operation::new("POST", "/api/v1/sim/{action}", "Control the active set's simulated robot: reset (the world's start, time 0), pose (x, y, heading: put it there, at rest), pause, resume, step (seconds: while paused, run the world forward)", "operator, admin (those who may drive). Answers the simulation's state after the action (pose, time_s, goal, distance, collisions, ranges).")
            .param(Param::bare("action").one_of(&["reset", "pose", "pause", "resume", "step"]))
            .param(Param::query_number("x", "pose: metres"))
            .param(Param::query_number("y", "pose: metres"))
            .param(Param::query_number("heading", "pose: radians"))
            .param(Param::query_number("seconds", "step: more than 0, at most 10"))
            .ok(200, "done; the simulation's state", Some(typed::<SimStatus>()))
            .error(400, "a query parameter is missing or not a number")
            .error(401, "not logged in")
            .error(403, "no permission")
            .error(404, "no such action, or the active set has no simulated robot")
            .error(409, "refused now: a pose inside an obstacle, a step while running, a step out of range")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("GET", "/api/v1/logs", "Recent log lines", "any user; a line naming a researcher's work (its owners: an upload, an activation, a component's line while her set runs) only to her and the admins")
            .ok(200, "the lines", Some(envelope([("lines", of::<Vec<LogLine>>)])))
            .error(401, "not logged in"),
        Operation::new("GET", "/api/v1/audit", "The audit log: who uploaded, activated, rolled back what, when, with what result", "developer, admin; a developer gets no researcher's entries")
            .ok(200, "the entries", Some(envelope([("entries", of::<Vec<AuditEntry>>)])))
            .error(401, "not logged in")
            .error(403, "no permission"),
        Operation::new("POST", "/api/v1/teleop/ticket", "A one-time ticket to authenticate on the teleoperation WebSocket (valid 60 s)", "operator, admin")
            .ok(200, "the ticket", Some(envelope([("name", of::<String>), ("ticket", of::<String>), ("websocket", of::<String>)])))
            .error(401, "not logged in")
            .error(403, "may not drive")
            .error(404, "no network platform")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("GET", "/api/v1/teleop", "WebSocket: the network platform's JSON protocol (docs/teleop.md); authenticate with {type: auth, name, token: ticket or password}", "authenticated inside the protocol")
            .anyone()
            .ok(101, "switching protocols", None)
            .error(400, "not a WebSocket upgrade request")
            .error(404, "no network platform")
            .error(503, "busy: too many connections that have not logged in (from this address, or in all; docs/teleop.md)"),
        Operation::new("GET", "/api/v1/openapi.json", "This document", "none")
            .anyone()
            .ok(200, "the OpenAPI document", Some(Content::Json(any_object))),
        Operation::new("POST", "/api/v1/estop", "Engage the emergency stop (lock 'estop'): every motion source below it is suppressed and the motors get STOP (docs/estop.md)", "every logged-in user, viewers included. Engaging an engaged lock changes nothing (the first engagement stands).")
            .ok(200, "the lock, whether this request engaged it (`newly`) and every engaged lock", Some(typed::<Engaged>()))
            .error(401, "not logged in")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("POST", "/api/v1/release", "Release a lock (body {\"lock\": NAME}) or every engaged lock (no body)", "operator, admin (a role that may drive). A refused release is in the audit log.")
            .body(Content::Json(release_body), false)
            .ok(200, "the released locks and how long each was engaged (ms)", Some(envelope([("released", of::<Vec<Released>>)])))
            .error(400, "a body that is not {\"lock\": NAME}")
            .error(401, "not logged in")
            .error(403, "may not drive")
            .error(409, "no such lock is engaged")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("GET", "/api/v1/locks", "The engaged locks (who, how, since when) and the latest engage and release events", "every logged-in user")
            .ok(200, "engaged locks, events (at most 256) and how many events there were", Some(typed::<LocksView>()))
            .error(401, "not logged in"),
        Operation::new("GET", "/api/v1/recordings", "The running recording (or null) and the files of the host's recordings folder (name, bytes, modified_unix_ms, recording)", "developers and admins (a recording holds every value, log line and round-trip time)")
            .ok(200, "{recording, files}", Some(typed::<RecordingsView>()))
            .error(401, "not logged in")
            .error(403, "viewers and operators may not record"),
        Operation::new("POST", "/api/v1/recordings/start", "Start recording the running robot to MCAP in the host's recordings folder, under a name the host makes up; the size limit and rotation of --record-max-mib apply. Body (optional) {\"fresh_start\": true}: re-activate the active set (built beside the running graph, swapped in at a cycle boundary, as an activation) and attach the recording at that swap, so every WASM component starts inside it and a replay of it is exact from the first call; audited as an activation and a recording start. Audited", "developers and admins (a recording holds every value, log line and round-trip time)")
            .body(typed::<StartRecording>(), false)
            .ok(201, "{recording: {name, by, started_unix_ms, fresh_start}}", Some(envelope([("recording", of::<RecordingInfo>)])))
            .error(400, "the body is neither empty nor {\"fresh_start\": BOOL}")
            .error(401, "not logged in")
            .error(403, "viewers and operators may not record")
            .error(409, "a recording runs already, the run records with --record or --foxglove, or the folder is full (a fresh start is refused so before anything is rebuilt)")
            .error(422, "fresh start: the active set no longer validates or a component failed to start (nothing changed)")
            .error(500, "fresh start: the control loop did not take the new graph (nothing changed, no recording)")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("POST", "/api/v1/recordings/stop", "Stop the running recording: what is queued, the summary and the footer are written. Audited", "developers and admins (a recording holds every value, log line and round-trip time)")
            .ok(200, "{stopped: {name, by, files, messages, bytes, dropped}}", Some(envelope([("stopped", of::<Stopped>)])))
            .error(401, "not logged in")
            .error(403, "viewers and operators may not record")
            .error(409, "no recording is running")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("GET", "/api/v1/recordings/{name}", "Download a recording file (application/octet-stream)", "developers and admins (a recording holds every value, log line and round-trip time)")
            .param(Param::path("name", "a recording file name as GET /api/v1/recordings lists it (rec-DATE-TIME-N.mcap, rotations rec-...-N.1.mcap)"))
            .ok(200, "the file's bytes", Some(bytes("application/octet-stream")))
            .error(400, "not a recording name")
            .error(401, "not logged in")
            .error(403, "viewers and operators may not record")
            .error(404, "no such recording"),
        Operation::new("DELETE", "/api/v1/recordings/{name}", "Delete a recording file (not one the running recording writes). Audited", "developers and admins (a recording holds every value, log line and round-trip time)")
            .param(Param::path("name", "a recording file name as GET /api/v1/recordings lists it (rec-DATE-TIME-N.mcap, rotations rec-...-N.1.mcap)"))
            .ok(200, "{deleted}", Some(envelope([("deleted", of::<String>)])))
            .error(400, "not a recording name")
            .error(401, "not logged in")
            .error(403, "viewers and operators may not record")
            .error(404, "no such recording")
            .error(409, "the running recording writes it")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("GET", "/api/v1/experiments", "The caller's experiments (an admin's: every one), newest first, each with its states and their times, reasons, preflight and run results, place in the queue and ETA while queued, end while it runs (docs/lab.md)", "any user (each sees only their own; admins see every one)")
            .ok(200, "{experiments: [...]}", Some(envelope([("experiments", of::<Vec<ExperimentView>>)])))
            .error(401, "not logged in"),
        Operation::new("POST", "/api/v1/experiments", "Submit a staged set as an experiment: checked at once (permission, duration, the set validates against the baseline, the per-user limits), then run in the simulator first (preflight), queued, run on the robot from a fresh start while recording, and given back as a results bundle. Audited", "researchers, developers and admins, for sets of platforms they hold")
            .body(typed::<Submission>(), true)
            .ok(201, "{experiment: {...}} in state checking", Some(envelope([("experiment", of::<ExperimentRecord>)])))
            .error(400, "a malformed body, a label too long, or a duration outside 1 s to the robot's max-duration")
            .error(401, "not logged in")
            .error(403, "the caller may not submit, or the set changes a platform the caller does not hold or the envelope")
            .error(404, "no such set")
            .error(422, "the set does not validate (the diagnostics subsume check prints)")
            .error(429, "over a per-user limit (experiments waiting, robot-minutes a day); the message says when it frees, Retry-After when known")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("GET", "/api/v1/experiments/{id}", "One experiment", "its submitter and admins (anyone else gets 404, as for one that does not exist)")
            .param(Param::path("id", "an experiment's id").integer(true))
            .ok(200, "{experiment: {...}}", Some(envelope([("experiment", of::<ExperimentView>)])))
            .error(400, "the id is not a number")
            .error(401, "not logged in")
            .error(404, "no such experiment (or not the caller's)"),
        Operation::new("POST", "/api/v1/experiments/{id}/cancel", "Cancel an experiment while it waits or runs; a running one ends with the baseline back (the answer waits for that). Audited", "its submitter and admins")
            .param(Param::path("id", "an experiment's id").integer(true))
            .ok(200, "{experiment: {...}} (cancelled)", Some(envelope([("experiment", of::<ExperimentRecord>)])))
            .error(400, "the id is not a number")
            .error(401, "not logged in")
            .error(404, "no such experiment (or not the caller's)")
            .error(409, "it has ended already"),
        Operation::new("GET", "/api/v1/experiments/{id}/results", "The results bundle as one tar archive (application/x-tar): experiment.json, robot.xml and components/ (replay with subsume replay run.mcap robot.xml), run.mcap, report.json, log.txt, the preflight's recording, report and verdict, SHA256SUMS", "its submitter and admins")
            .param(Param::path("id", "an experiment's id").integer(true))
            .ok(200, "the archive", Some(bytes("application/x-tar")))
            .error(400, "the id is not a number")
            .error(401, "not logged in")
            .error(404, "no such experiment (or not the caller's)")
            .error(409, "it has not ended yet"),
        Operation::new("GET", "/api/v1/lab", "The lab: the experiment on the robot (who, which set, when it ends), the queue's length, whether it is paused or held (a lock, a manual reset), the baseline, the reservations, the host's clock (now_unix_ms, to count down by); the owner's settings for admins", "any user")
            .ok(200, "{lab: {...}}", Some(envelope([("lab", of::<LabView>)])))
            .error(401, "not logged in"),
        Operation::new("GET", "/api/v1/lab/events", "Server-sent events: `lab` with {lab, experiments} (the caller's) at once and at every change", "any user")
            .ok(200, "text/event-stream", Some(text("text/event-stream")))
            .error(401, "not logged in"),
        Operation::new("PUT", "/api/v1/lab/settings", "Change the owner's settings (max-duration, per-user limits, preflight criteria, reset policy, preflight world, reference recording, retention, the lab kit). Audited", "admins")
            .body(typed::<LabSettings>(), true)
            .body_description("the owner's settings, as GET /api/v1/lab shows them to an admin")
            .ok(200, "{settings}", Some(envelope([("settings", of::<LabSettings>)])))
            .error(400, "a malformed body or a value out of range")
            .error(401, "not logged in")
            .error(403, "not an admin")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("PUT", "/api/v1/lab/baseline", "Mark a set as the baseline, the set the robot runs between experiments (it must validate). Audited", "admins")
            .body(typed::<BaselineRequest>(), true)
            .ok(200, "{baseline}", Some(envelope([("baseline", of::<u64>)])))
            .error(400, "a malformed body")
            .error(401, "not logged in")
            .error(403, "not an admin")
            .error(404, "no such set")
            .error(422, "the set does not validate")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("POST", "/api/v1/lab/pause", "Pause the queue: nothing new starts; what runs goes on. Audited", "admins")
            .ok(200, "{paused: true}", Some(envelope([("paused", of::<bool>)])))
            .error(401, "not logged in")
            .error(403, "not an admin")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("POST", "/api/v1/lab/resume", "Resume the queue. Audited", "admins")
            .ok(200, "{paused: false}", Some(envelope([("paused", of::<bool>)])))
            .error(401, "not logged in")
            .error(403, "not an admin")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("POST", "/api/v1/lab/reset", "Confirm the robot was put back at its start for the experiment that waits for it (the manual reset policy). Audited", "admins")
            .ok(200, "{confirmed_for}", Some(envelope([("confirmed_for", of::<u64>)])))
            .error(401, "not logged in")
            .error(403, "not an admin")
            .error(409, "no experiment waits for a reset"),
        Operation::new("POST", "/api/v1/lab/reservations", "Book a window in which only the holder's experiments run and the holder may drive; windows never overlap and are bounded by the owner's limits. Audited", "researchers, developers and admins (for themselves; admins for anyone)")
            .body(typed::<BookingRequest>(), true)
            .ok(201, "{reservation: {id, user, start_ms, end_ms}}", Some(envelope([("reservation", of::<Reservation>)])))
            .error(400, "a malformed body, a window backwards, over, too long or too far ahead")
            .error(401, "not logged in")
            .error(403, "the caller may not book, or not for someone else")
            .error(404, "on a lab server, always: it takes no reservations (docs/lab.md, \"Several robots\")")
            .error(409, "it overlaps another reservation, or the lab holds the most it keeps")
            .error(429, "over the day's reserved minutes")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("DELETE", "/api/v1/lab/reservations/{id}", "Cancel a reservation. Audited", "its holder and admins")
            .param(Param::path("id", "a reservation's id").integer(true))
            .ok(200, "{cancelled}", Some(envelope([("cancelled", of::<u64>)])))
            .error(400, "the id is not a number")
            .error(401, "not logged in")
            .error(404, "no such reservation (or not the caller's); on a lab server, always: it takes no reservations (docs/lab.md, \"Several robots\")")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("GET", "/api/v1/lab/kit", "The lab kit as a tar archive: the baseline's robot file in its preflight form with its components and world, the preflight criteria and a README: subsume run robot.xml --speed max --criteria criteria.json gives the preflight's verdict. Audited", "researchers, developers and admins, unless the owner turned the kit off (admins always)")
            .ok(200, "the archive", Some(bytes("application/x-tar")))
            .error(401, "not logged in")
            .error(403, "the caller may not, or the kit is off"),
        Operation::new("POST", "/api/v1/lab/maintenance", "Take the robot out of service, with a reason: no experiment starts until an admin ends it (queued ones wait, with the reason and no ETA). Stored; audited; the owner's webhooks and mail are told", "admins")
            .body(typed::<MaintenanceRequest>(), true)
            .ok(200, "{maintenance}", Some(envelope([("maintenance", of::<Maintenance>)])))
            .error(400, "a malformed body or an empty or overlong reason")
            .error(401, "not logged in")
            .error(403, "not an admin")
            .error(409, "the robot (on a lab server: the lab) is in maintenance already")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("DELETE", "/api/v1/lab/maintenance", "Bring the robot back into service. Audited; the owner's webhooks and mail are told", "admins")
            .ok(200, "{maintenance: null}", Some(envelope([("maintenance", of::<()>)])))
            .error(401, "not logged in")
            .error(403, "not an admin")
            .error(409, "the robot (on a lab server: the lab) is not in maintenance")
            .error(507, "the robot's disk is full: nothing of the request was kept"),
        Operation::new("POST", "/api/v1/lab/selftest", "Run the owner's self-test now, on the idle robot (docs/lab.md, Self-test): kept in the history; a failed one takes the robot out of service, a passed one ends a maintenance the self-test began. Audited", "admins")
            .ok(200, "{self_test: {at_ms, experiment, passed, checks}}", Some(envelope([("self_test", of::<SelfTest>)])))
            .error(401, "not logged in")
            .error(403, "not an admin")
            .error(409, "the settings have no self-test, an experiment runs, or a self-test runs already")
            .error(507, "the robot's disk is full: the result was not kept"),
        Operation::new("GET", "/api/v1/lab/mail", "The caller's own mail subscription (null when she has none)", "any user")
            .ok(200, "{mail}", Some(envelope([("mail", of::<Option<MailSubscription>>)])))
            .error(401, "not logged in")
            .error(409, "this lab sends no mail (its owner configured no mail.json)"),
        Operation::new("PUT", "/api/v1/lab/mail", "Mail the caller about her own experiments: an address and the events (accepted, refused, started, ended). Audited", "any user")
            .body(typed::<MailSubscription>(), true)
            .body_description("where the lab mails the caller, and for which events of her own experiments")
            .ok(200, "{mail}", Some(envelope([("mail", of::<Option<MailSubscription>>)])))
            .error(400, "a malformed body, an address SMTP does not take, or an event that is not one of her own experiments'")
            .error(401, "not logged in")
            .error(409, "this lab sends no mail (its owner configured no mail.json)")
            .error(500, "the subscription could not be kept"),
        Operation::new("DELETE", "/api/v1/lab/mail", "End the caller's own mail subscription. Audited", "any user")
            .ok(200, "{mail: null}", Some(envelope([("mail", of::<Option<MailSubscription>>)])))
            .error(401, "not logged in")
            .error(409, "this lab sends no mail (its owner configured no mail.json)")
            .error(500, "the subscription could not be kept"),
        Operation::new("GET", "/api/v1/robots", "A lab server's robots (docs/lab.md, \"Several robots\"): each one's name, profile (worlds, translators, baseline hash), state (idle, running, stopped, maintenance, lost), the lab's experiment it runs and its time left, its locks, when it was last seen", "any user")
            .ok(200, "{robots: [{name, state, online, experiment, ends_unix_ms, time_left_s, stopped_by, locks, profile, max_duration_s, baseline_set, baseline_error, last_seen_unix_ms}]}", Some(envelope([("robots", of::<Vec<RobotView>>)])))
            .error(401, "not logged in")
            .error(404, "this host is one robot, not a lab server (subsume lab serve); or no such robot"),
        Operation::new("POST", "/api/v1/robots/stop", "The lab's STOP for every robot: engages each robot's emergency stop over the lab's link; each robot's answer. Audited", "any user")
            .ok(200, "{stopped: [{robot, engaged, message}]}", Some(envelope([("stopped", of::<Vec<RobotStop>>)])))
            .error(401, "not logged in")
            .error(404, "this host is one robot, not a lab server (subsume lab serve); or no such robot"),
        Operation::new("GET", "/api/v1/robots/{name}/live", "One robot's live status, asked of it now over the lab's link", "any user")
            .param(Param::bare("name"))
            .ok(200, "{status: {...}}", Some(envelope([("status", any_object)])))
            .error(401, "not logged in")
            .error(404, "this host is one robot, not a lab server (subsume lab serve); or no such robot")
            .error(500, "the robot did not answer"),
        Operation::new("POST", "/api/v1/robots/{name}/stop", "The lab's STOP for one robot: engages its emergency stop over the lab's link. Audited", "any user")
            .param(Param::bare("name"))
            .ok(200, "{stopped: [{robot, engaged, message}]}", Some(envelope([("stopped", of::<Vec<RobotStop>>)])))
            .error(401, "not logged in")
            .error(404, "this host is one robot, not a lab server (subsume lab serve); or no such robot"),
        Operation::new("GET", "/api/v1/tasks/{name}/leaderboard", "A task's leaderboard: each user's best (or latest, the owner's choice) scored run, ranked by the task's metric (docs/lab.md, Leaderboard)", "any user of the lab. Others are shown as participant-N unless the owner turned pseudonyms off; admins see every name and experiment id.")
            .param(Param::path("name", "the owner's task's name"))
            .ok(200, "{leaderboard: {task, description, metric, better, board, entries}}", Some(envelope([("leaderboard", of::<Board>)])))
            .error(401, "not logged in")
            .error(404, "the lab has no task of that name"),
    ]
}

/// `GET /sets` lists each set as its record without the wiring (that is
/// for one set's page) and with its status (`portal::routes::list_sets`).
fn listed_sets(generator: &mut SchemaGenerator) -> Schema {
    let mut set = generator.subschema_for::<SetRecord>();
    let status = generator.subschema_for::<SetStatus>().to_value();
    if let Some(properties) = set.get_mut("properties").and_then(Value::as_object_mut) {
        properties.remove("graph");
        properties.insert("status".into(), status);
    }
    if let Some(required) = set.get_mut("required").and_then(Value::as_array_mut) {
        required.retain(|name| name != "graph");
        required.push("status".into());
    }
    schemars::json_schema!({ "type": "array", "items": set })
}

/// `POST /release`'s body, read by hand (`portal::routes::release`): no
/// body, or `lock` a string (or null).
fn release_body(_: &mut SchemaGenerator) -> Schema {
    schemars::json_schema!({
        "type": "object",
        "properties": { "lock": { "type": ["string", "null"], "description": "the lock to release; every engaged lock when missing" } },
    })
}
