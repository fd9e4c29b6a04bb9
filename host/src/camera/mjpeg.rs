//! The IP camera source of `builtin:camera` (`source="http://HOST:PORT/PATH"`):
//! JPEG frames streamed over HTTP/1.1 as `multipart/x-mixed-replace`
//! ("MJPEG over HTTP"), what most IP cameras and `ffmpeg -f mpjpeg` serve
//! (docs/camera.md, "An IP camera").
//!
//! Everything here runs on the camera's own thread, never on the control
//! loop. The connection is a plain [`TcpStream`] whose every read waits at
//! most until the frame deadline ([`FRAME_TIMEOUT`] after the last whole
//! frame), so a camera that stalls, or dribbles, is dropped and dialled
//! again after a backoff ([`RECONNECT_MIN`] doubling to [`RECONNECT_MAX`]).
//! The response head is parsed by `httparse`, which also reads the chunk
//! sizes of a chunked body (ffmpeg's server sends one); the parts are split
//! on their boundary here, each bounded by [`MAX_FRAME_BYTES`]. A part is a
//! frame when it is a whole JPEG file: start and end markers, and a frame
//! header that `zune-jpeg` reads (width and height within the camera's
//! limits). The JPEG bytes are passed through as the camera sent them:
//! nothing here decodes or encodes a picture.

use std::cell::Cell;
use std::io::{self, BufRead, BufReader, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpStream, ToSocketAddrs};
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use super::{MAX_HEIGHT_PX, MAX_WIDTH_PX};

/// Largest frame (one JPEG file) accepted: the camera's thread holds up to
/// this much per frame, and every listener and the recorder get a copy. A
/// 1920x1080 picture at high quality is well under 1 MiB; a larger part is
/// read past, dropped and counted.
pub const MAX_FRAME_BYTES: usize = 4 * 1024 * 1024;
/// How long dialling the camera may take: a camera that is off or
/// unreachable must not keep the thread from trying again (nor from
/// stopping).
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);
/// Longest wait for the next whole frame (from the connection or from the
/// frame before): a camera that stops sending, or sends a frame a byte at a
/// time, is a stalled camera; the connection is dropped and dialled again.
pub const FRAME_TIMEOUT: Duration = Duration::from_secs(5);
/// First wait before dialling again after a failure; each failure in a row
/// doubles it up to [`RECONNECT_MAX`], so a broken camera costs at most one
/// connection attempt per [`RECONNECT_MAX`].
pub const RECONNECT_MIN: Duration = Duration::from_millis(200);
pub const RECONNECT_MAX: Duration = Duration::from_secs(5);
/// Largest response head and largest set of part headers: more is not an
/// MJPEG camera.
pub const MAX_HEAD_BYTES: usize = 16 * 1024;
/// Longest line (boundary, part header, chunk size) before a frame: a
/// longer one means the stream lost its framing.
pub const MAX_LINE_BYTES: usize = 1024;
/// Most headers in the response or in one part.
pub const MAX_HEADERS: usize = 32;
/// Longest `source` URL: it is shown in errors and the status.
pub const MAX_URL_BYTES: usize = 2048;
/// Bytes read from the socket at a time.
const READ_BYTES: usize = 64 * 1024;
/// Blank lines tolerated between parts.
const MAX_BLANK_LINES: usize = 4;

/// An `http://` source, as the robot file names it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct HttpSource {
    pub host: String,
    pub port: u16,
    /// The path and query, starting with `/`.
    pub path: String,
}

impl std::fmt::Display for HttpSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.host.contains(':') {
            write!(f, "http://[{}]:{}{}", self.host, self.port, self.path)
        } else {
            write!(f, "http://{}:{}{}", self.host, self.port, self.path)
        }
    }
}

/// Why a `source` is not an `http://` camera this host can read.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum UrlError {
    #[error("is not an http:// URL")]
    NotHttp,
    #[error("is longer than {MAX_URL_BYTES} bytes")]
    TooLong,
    #[error("names no host")]
    NoHost,
    #[error("has a host with characters a host name cannot have: '{0}'")]
    BadHost(String),
    #[error("has a port that is not a number from 1 to 65535: '{0}'")]
    BadPort(String),
    #[error("carries a user name or password (not supported: a robot file is no place for a camera's password)")]
    Credentials,
    #[error("has spaces or control characters in its path")]
    BadPath,
}

/// `source` as an `http://HOST[:PORT][/PATH]` camera.
pub fn parse_source(source: &str) -> Result<HttpSource, UrlError> {
    if source.len() > MAX_URL_BYTES {
        return Err(UrlError::TooLong);
    }
    let rest = source
        .get(..7)
        .filter(|scheme| scheme.eq_ignore_ascii_case("http://"))
        .map(|_| &source[7..])
        .ok_or(UrlError::NotHttp)?;
    let rest = rest.split('#').next().unwrap_or_default();
    let (authority, path) = match rest.find(['/', '?']) {
        Some(at) if rest[at..].starts_with('/') => (&rest[..at], rest[at..].to_string()),
        Some(at) => (&rest[..at], format!("/{}", &rest[at..])),
        None => (rest, "/".to_string()),
    };
    if authority.contains('@') {
        return Err(UrlError::Credentials);
    }
    if path.chars().any(|c| c.is_control() || c.is_whitespace()) {
        return Err(UrlError::BadPath);
    }
    let (host, port) = if let Some(v6) = authority.strip_prefix('[') {
        let (host, after) = v6.split_once(']').ok_or_else(|| UrlError::BadHost(authority.into()))?;
        if host.is_empty() || !host.chars().all(|c| c.is_ascii_hexdigit() || c == ':' || c == '.') {
            return Err(UrlError::BadHost(host.into()));
        }
        match after {
            "" => (host, None),
            _ => (host, Some(after.strip_prefix(':').ok_or_else(|| UrlError::BadPort(after.into()))?)),
        }
    } else {
        match authority.rsplit_once(':') {
            Some((host, port)) => (host, Some(port)),
            None => (authority, None),
        }
    };
    if host.is_empty() {
        return Err(UrlError::NoHost);
    }
    if !authority.starts_with('[') && !host.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_')) {
        return Err(UrlError::BadHost(host.into()));
    }
    let port = match port {
        None => 80,
        Some(port) => port.parse::<u16>().ok().filter(|p| *p != 0).ok_or_else(|| UrlError::BadPort(port.into()))?,
    };
    Ok(HttpSource { host: host.to_string(), port, path })
}

/// Why a part of the stream was not a frame: it is dropped and counted, and
/// the stream goes on.
#[derive(Clone, Debug, thiserror::Error, PartialEq, Eq)]
pub enum Reject {
    #[error("a frame of {0} bytes is larger than the limit ({MAX_FRAME_BYTES} bytes)")]
    TooLarge(usize),
    #[error("a part is not a JPEG file ({0})")]
    NotJpeg(&'static str),
    #[error("a JPEG frame's header does not decode: {0}")]
    Undecodable(String),
    #[error("a {0}x{1} frame is larger than {MAX_WIDTH_PX}x{MAX_HEIGHT_PX}")]
    TooWide(usize, usize),
}

impl Reject {
    /// A name for the kind of fault (the log says each once).
    pub fn kind(&self) -> &'static str {
        match self {
            Reject::TooLarge(_) => "too-large",
            Reject::NotJpeg(_) => "not-jpeg",
            Reject::Undecodable(_) => "undecodable",
            Reject::TooWide(..) => "too-wide",
        }
    }
}

/// Why the connection was given up: the camera is dialled again after the
/// backoff.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    #[error("cannot resolve the camera's host: {0}")]
    Resolve(io::Error),
    #[error("cannot connect: {0}")]
    Connect(io::Error),
    #[error("no whole frame for {} s (the camera stalled)", FRAME_TIMEOUT.as_secs())]
    Stalled,
    #[error("the camera closed the stream")]
    Ended,
    #[error("the camera answered HTTP {0}")]
    Status(u16),
    #[error("the answer is not HTTP: {0}")]
    NotHttp(String),
    #[error("the answer is a single picture (Content-Type image/jpeg), not an MJPEG stream")]
    SinglePicture,
    #[error("the stream lost its multipart framing: {0}")]
    LostSync(&'static str),
    #[error("reading the stream: {0}")]
    Io(io::Error),
}

impl StreamError {
    /// A name for the kind of fault (the log says each once).
    pub fn kind(&self) -> &'static str {
        match self {
            StreamError::Resolve(_) => "resolve",
            StreamError::Connect(_) => "connect",
            StreamError::Stalled => "stalled",
            StreamError::Ended => "ended",
            StreamError::Status(_) => "status",
            StreamError::NotHttp(_) => "not-http",
            StreamError::SinglePicture => "single-picture",
            StreamError::LostSync(_) => "lost-sync",
            StreamError::Io(_) => "io",
        }
    }
}

impl From<io::Error> for StreamError {
    fn from(e: io::Error) -> StreamError {
        match e.kind() {
            io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock => StreamError::Stalled,
            io::ErrorKind::UnexpectedEof => StreamError::Ended,
            io::ErrorKind::InvalidData => StreamError::LostSync("a chunk size did not parse"),
            _ => StreamError::Io(e),
        }
    }
}

/// `data` as a frame: its width and height, or why it is none.
pub fn check_jpeg(data: &[u8]) -> Result<(u16, u16), Reject> {
    if data.len() > MAX_FRAME_BYTES {
        return Err(Reject::TooLarge(data.len()));
    }
    if !data.starts_with(&[0xff, 0xd8]) {
        return Err(Reject::NotJpeg("no start-of-image marker"));
    }
    if !data.ends_with(&[0xff, 0xd9]) {
        return Err(Reject::NotJpeg("no end-of-image marker"));
    }
    let mut decoder = zune_jpeg::JpegDecoder::new(data);
    decoder.decode_headers().map_err(|e| Reject::Undecodable(crate::contract::clip_to(&e.to_string(), 120)))?;
    let (width, height) = decoder.dimensions().ok_or(Reject::Undecodable("no frame header".into()))?;
    let fits = |side: usize, max: i64| i64::try_from(side).is_ok_and(|s| s <= max) && side > 0;
    if !fits(width, MAX_WIDTH_PX) || !fits(height, MAX_HEIGHT_PX) {
        return Err(Reject::TooWide(width, height));
    }
    match (u16::try_from(width), u16::try_from(height)) {
        (Ok(w), Ok(h)) => Ok((w, h)),
        _ => Err(Reject::TooWide(width, height)),
    }
}

/// A socket whose reads wait at most until a shared deadline.
struct Timed {
    tcp: TcpStream,
    deadline: Rc<Cell<Instant>>,
}

impl Read for Timed {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let left = self.deadline.get().saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(io::ErrorKind::TimedOut.into());
        }
        self.tcp.set_read_timeout(Some(left))?;
        self.tcp.read(buf)
    }
}

/// A chunked body's data (RFC 9112 7.1); chunk sizes read by `httparse`.
struct Chunked<R> {
    inner: R,
    /// Bytes left in the current chunk.
    left: u64,
    /// The last chunk was read.
    done: bool,
}

impl<R: BufRead> Chunked<R> {
    fn size_line(&mut self) -> io::Result<u64> {
        let mut line = Vec::new();
        (&mut self.inner).take(MAX_LINE_BYTES as u64).read_until(b'\n', &mut line)?;
        if line.is_empty() {
            return Err(io::ErrorKind::UnexpectedEof.into());
        }
        match httparse::parse_chunk_size(&line) {
            Ok(httparse::Status::Complete((_, size))) => Ok(size),
            _ => Err(io::Error::new(io::ErrorKind::InvalidData, "bad chunk size")),
        }
    }
}

impl<R: BufRead> Read for Chunked<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.done || buf.is_empty() {
            return Ok(0);
        }
        if self.left == 0 {
            self.left = self.size_line()?;
            if self.left == 0 {
                self.done = true;
                return Ok(0);
            }
        }
        let want = usize::try_from(self.left).unwrap_or(usize::MAX).min(buf.len());
        let got = self.inner.read(&mut buf[..want])?;
        if got == 0 {
            return Err(io::ErrorKind::UnexpectedEof.into());
        }
        self.left -= got as u64;
        if self.left == 0 {
            let mut crlf = [0; 2];
            self.inner.read_exact(&mut crlf)?;
            if crlf != *b"\r\n" {
                return Err(io::Error::new(io::ErrorKind::InvalidData, "no CRLF after a chunk"));
            }
        }
        Ok(got)
    }
}

/// One part of the multipart stream.
#[derive(Debug, PartialEq, Eq)]
pub enum Part {
    /// A whole JPEG file with its width and height.
    Frame { jpeg: Vec<u8>, width: u16, height: u16 },
    /// A part that is not a frame.
    Rejected(Reject),
}

/// Splits a multipart body into parts.
pub struct Parts<R> {
    src: R,
    buf: Vec<u8>,
    start: usize,
    /// The boundary (without its leading `--`): from the Content-Type, or
    /// learnt from the first boundary line when the server sent none
    /// (ffmpeg's server says `application/octet-stream`).
    boundary: Option<Vec<u8>>,
}

impl<R: Read> Parts<R> {
    pub fn new(src: R, boundary: Option<Vec<u8>>) -> Parts<R> {
        Parts { src, buf: Vec::new(), start: 0, boundary }
    }

    fn held(&self) -> &[u8] {
        &self.buf[self.start..]
    }

    /// Reads more bytes into the buffer.
    fn more(&mut self) -> Result<(), StreamError> {
        if self.start > 0 {
            self.buf.drain(..self.start);
            self.start = 0;
        }
        let len = self.buf.len();
        self.buf.resize(len + READ_BYTES, 0);
        let got = loop {
            match self.src.read(&mut self.buf[len..]) {
                Ok(got) => break got,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => {
                    self.buf.truncate(len);
                    return Err(e.into());
                }
            }
        };
        self.buf.truncate(len + got);
        if got == 0 {
            return Err(StreamError::Ended);
        }
        Ok(())
    }

    /// The next line, without its CRLF.
    fn line(&mut self) -> Result<Vec<u8>, StreamError> {
        loop {
            if let Some(at) = self.held().iter().position(|b| *b == b'\n') {
                let mut line = self.held()[..at].to_vec();
                self.start += at + 1;
                if line.last() == Some(&b'\r') {
                    line.pop();
                }
                return Ok(line);
            }
            if self.held().len() > MAX_LINE_BYTES {
                return Err(StreamError::LostSync("a line before a frame is too long"));
            }
            self.more()?;
        }
    }

    /// Reads past `n` bytes.
    fn skip(&mut self, mut n: usize) -> Result<(), StreamError> {
        loop {
            let here = n.min(self.held().len());
            self.start += here;
            n -= here;
            if n == 0 {
                return Ok(());
            }
            self.more()?;
        }
    }

    /// The next `n` bytes.
    fn exact(&mut self, n: usize) -> Result<Vec<u8>, StreamError> {
        while self.held().len() < n {
            self.more()?;
        }
        let data = self.held()[..n].to_vec();
        self.start += n;
        Ok(data)
    }

    /// The bytes before the next `CRLF--boundary` (left to be read), or
    /// [`Reject::TooLarge`] once more than [`MAX_FRAME_BYTES`] came before it.
    fn until_boundary(&mut self, boundary: &[u8]) -> Result<Part, StreamError> {
        let mut needle = b"\r\n--".to_vec();
        needle.extend_from_slice(boundary);
        let mut searched = 0;
        let mut skipped = 0usize;
        loop {
            if let Some(at) = find(&self.held()[searched..], &needle).map(|at| at + searched) {
                if skipped > 0 {
                    self.start += at + 2;
                    return Ok(Part::Rejected(Reject::TooLarge(skipped + at)));
                }
                let data = self.held()[..at].to_vec();
                self.start += at + 2;
                return Ok(match check_jpeg(&data) {
                    Ok((width, height)) => Part::Frame { jpeg: data, width, height },
                    Err(why) => Part::Rejected(why),
                });
            }
            let held = self.held().len();
            searched = held.saturating_sub(needle.len());
            if held > MAX_FRAME_BYTES + needle.len() {
                // Too large: keep only what may begin the boundary.
                skipped += searched;
                self.start += searched;
                searched = 0;
                if skipped > 4 * MAX_FRAME_BYTES {
                    return Err(StreamError::LostSync("no boundary in four times the largest frame"));
                }
            }
            self.more()?;
        }
    }

    /// The next part.
    pub fn next_part(&mut self) -> Result<Part, StreamError> {
        // The boundary line (after the CRLF ending the part before).
        let mut blank = 0;
        let boundary = loop {
            let line = self.line()?;
            let line = line.trim_ascii_end();
            if line.is_empty() {
                blank += 1;
                if blank > MAX_BLANK_LINES {
                    return Err(StreamError::LostSync("blank lines where a boundary should be"));
                }
                continue;
            }
            let Some(named) = line.strip_prefix(b"--") else {
                return Err(StreamError::LostSync("no boundary where a part should begin"));
            };
            match &self.boundary {
                Some(boundary) if named == boundary.as_slice() => break boundary.clone(),
                Some(boundary) if named.strip_suffix(b"--") == Some(boundary.as_slice()) => {
                    return Err(StreamError::Ended);
                }
                Some(_) => return Err(StreamError::LostSync("a boundary that is not the stream's")),
                None if named.is_empty() => return Err(StreamError::LostSync("an empty boundary")),
                None => {
                    self.boundary = Some(named.to_vec());
                    break named.to_vec();
                }
            }
        };
        // The part's headers.
        let mut length = None;
        let mut headers = 0;
        loop {
            let line = self.line()?;
            if line.is_empty() {
                break;
            }
            headers += 1;
            if headers > MAX_HEADERS {
                return Err(StreamError::LostSync("too many part headers"));
            }
            let Some(colon) = line.iter().position(|b| *b == b':') else {
                return Err(StreamError::LostSync("a part header without a colon"));
            };
            let (name, value) = (&line[..colon], &line[colon + 1..]);
            if name.trim_ascii().eq_ignore_ascii_case(b"content-length") {
                let value = std::str::from_utf8(value.trim_ascii()).ok().and_then(|v| v.parse::<usize>().ok());
                length = Some(value.ok_or(StreamError::LostSync("a Content-Length that is not a number"))?);
            }
        }
        match length {
            Some(n) if n > MAX_FRAME_BYTES => {
                self.skip(n)?;
                Ok(Part::Rejected(Reject::TooLarge(n)))
            }
            Some(n) => {
                let data = self.exact(n)?;
                Ok(match check_jpeg(&data) {
                    Ok((width, height)) => Part::Frame { jpeg: data, width, height },
                    Err(why) => Part::Rejected(why),
                })
            }
            None => self.until_boundary(&boundary),
        }
    }
}

/// Where `needle` first occurs in `hay`.
fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    if needle.is_empty() || hay.len() < needle.len() {
        return None;
    }
    hay.windows(needle.len()).position(|w| w == needle)
}

/// The boundary of a `multipart/...; boundary=B` content type.
fn boundary_of(content_type: &str) -> Option<Vec<u8>> {
    let mut fields = content_type.split(';');
    let kind = fields.next()?.trim();
    if !kind.to_ascii_lowercase().starts_with("multipart/") {
        return None;
    }
    fields.find_map(|field| {
        let (name, value) = field.split_once('=')?;
        if !name.trim().eq_ignore_ascii_case("boundary") {
            return None;
        }
        let value = value.trim().trim_matches('"');
        // Some cameras write the boundary with its leading dashes.
        let value = value.strip_prefix("--").unwrap_or(value);
        (!value.is_empty()).then(|| value.as_bytes().to_vec())
    })
}

/// An open MJPEG stream.
pub struct Stream {
    parts: Parts<Box<dyn Read>>,
    deadline: Rc<Cell<Instant>>,
}

impl Stream {
    /// Dials `source`, asks for its stream and reads the answer's head. The
    /// socket is put in `socket` too, so that another thread can shut it
    /// (stopping the camera interrupts a read): one that sets `stop` before
    /// shutting finds it there, or this sees `stop` and gives up.
    pub fn open(
        source: &HttpSource,
        socket: &Mutex<Option<TcpStream>>,
        stop: &AtomicBool,
    ) -> Result<Stream, StreamError> {
        let deadline = Rc::new(Cell::new(Instant::now() + FRAME_TIMEOUT));
        let addrs: Vec<SocketAddr> =
            (source.host.as_str(), source.port).to_socket_addrs().map_err(StreamError::Resolve)?.collect();
        let mut last = io::Error::new(io::ErrorKind::NotFound, "the host has no address");
        let mut tcp = None;
        for addr in addrs {
            match TcpStream::connect_timeout(&addr, CONNECT_TIMEOUT) {
                Ok(stream) => {
                    tcp = Some(stream);
                    break;
                }
                Err(e) => last = e,
            }
        }
        let mut tcp = tcp.ok_or(StreamError::Connect(last))?;
        let _ = tcp.set_nodelay(true);
        tcp.set_write_timeout(Some(CONNECT_TIMEOUT)).map_err(StreamError::Connect)?;
        if let Ok(clone) = tcp.try_clone() {
            *socket.lock().unwrap_or_else(PoisonError::into_inner) = Some(clone);
        }
        if stop.load(Ordering::SeqCst) {
            return Err(StreamError::Ended);
        }
        let host = if source.host.contains(':') { format!("[{}]", source.host) } else { source.host.clone() };
        let request = format!(
            "GET {} HTTP/1.1\r\nHost: {host}:{}\r\nUser-Agent: subsume/{}\r\nAccept: multipart/x-mixed-replace, */*\r\nConnection: close\r\n\r\n",
            source.path,
            source.port,
            env!("CARGO_PKG_VERSION"),
        );
        tcp.write_all(request.as_bytes()).map_err(StreamError::Connect)?;
        let mut reader = BufReader::with_capacity(READ_BYTES, Timed { tcp, deadline: deadline.clone() });

        // The head, line by line, so the reader stays at the body.
        let mut head = Vec::new();
        loop {
            let before = head.len();
            let room = (MAX_HEAD_BYTES + 1).saturating_sub(before) as u64;
            (&mut reader).take(room).read_until(b'\n', &mut head)?;
            if head.len() == before {
                return Err(StreamError::Ended);
            }
            if head.len() > MAX_HEAD_BYTES {
                return Err(StreamError::NotHttp(format!("no end of the head in {MAX_HEAD_BYTES} bytes")));
            }
            if head.ends_with(b"\r\n\r\n") || head.ends_with(b"\n\n") {
                break;
            }
        }
        let mut headers = [httparse::EMPTY_HEADER; MAX_HEADERS];
        let mut response = httparse::Response::new(&mut headers);
        match response.parse(&head) {
            Ok(httparse::Status::Complete(_)) => {}
            Ok(httparse::Status::Partial) => return Err(StreamError::NotHttp("an incomplete head".into())),
            Err(e) => return Err(StreamError::NotHttp(e.to_string())),
        }
        let code = response.code.unwrap_or(0);
        if code != 200 {
            return Err(StreamError::Status(code));
        }
        let header = |name: &str| {
            response
                .headers
                .iter()
                .find(|h| h.name.eq_ignore_ascii_case(name))
                .and_then(|h| std::str::from_utf8(h.value).ok())
                .map(str::trim)
        };
        let content_type = header("content-type").unwrap_or_default();
        if content_type.to_ascii_lowercase().starts_with("image/") {
            return Err(StreamError::SinglePicture);
        }
        let boundary = boundary_of(content_type);
        let chunked = header("transfer-encoding").is_some_and(|te| te.to_ascii_lowercase().contains("chunked"));
        let body: Box<dyn Read> =
            if chunked { Box::new(Chunked { inner: reader, left: 0, done: false }) } else { Box::new(reader) };
        Ok(Stream { parts: Parts::new(body, boundary), deadline })
    }

    /// The next part; the next whole frame must come within
    /// [`FRAME_TIMEOUT`] of the one before.
    pub fn next_part(&mut self) -> Result<Part, StreamError> {
        let part = self.parts.next_part()?;
        self.deadline.set(Instant::now() + FRAME_TIMEOUT);
        Ok(part)
    }
}

/// The socket of the open stream, to shut from another thread.
pub type Socket = Arc<Mutex<Option<TcpStream>>>;

/// Shuts `socket`, interrupting a read on the camera's thread.
pub fn shut(socket: &Socket) {
    if let Some(tcp) = socket.lock().unwrap_or_else(PoisonError::into_inner).take() {
        let _ = tcp.shutdown(Shutdown::Both);
    }
}

/// Waits `wait` unless `stop` is set first.
pub fn pause(wait: Duration, stop: &AtomicBool) {
    let until = Instant::now() + wait;
    while !stop.load(Ordering::Relaxed) {
        let left = until.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return;
        }
        std::thread::sleep(left.min(Duration::from_millis(20)));
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    fn jpeg(width: u16, height: u16) -> Vec<u8> {
        let settings = super::super::CameraSettings { width, height, period_ns: 1, quality: 50 };
        super::super::encode(&vec![90; usize::from(width) * usize::from(height) * 3], settings).unwrap()
    }

    #[test]
    fn http_sources_parse_and_others_are_refused_with_the_reason() {
        assert_eq!(
            parse_source("http://127.0.0.1:8080/video.mjpg"),
            Ok(HttpSource { host: "127.0.0.1".into(), port: 8080, path: "/video.mjpg".into() })
        );
        assert_eq!(
            parse_source("HTTP://cam.lab-1.local?action=stream"),
            Ok(HttpSource { host: "cam.lab-1.local".into(), port: 80, path: "/?action=stream".into() })
        );
        assert_eq!(parse_source("http://[::1]:81"), Ok(HttpSource { host: "::1".into(), port: 81, path: "/".into() }));
        assert_eq!(parse_source("http://[::1]:81").unwrap().to_string(), "http://[::1]:81/");
        assert_eq!(parse_source("rtsp://cam/stream"), Err(UrlError::NotHttp));
        assert_eq!(parse_source("https://cam/"), Err(UrlError::NotHttp));
        assert_eq!(parse_source("http://admin:secret@cam/"), Err(UrlError::Credentials));
        assert_eq!(parse_source("http://:80/"), Err(UrlError::NoHost));
        assert_eq!(parse_source("http://cam:0/"), Err(UrlError::BadPort("0".into())));
        assert_eq!(parse_source("http://cam:99999/"), Err(UrlError::BadPort("99999".into())));
        assert_eq!(parse_source("http://cam/a b"), Err(UrlError::BadPath));
        assert_eq!(parse_source("http://cam/a\r\nX: y"), Err(UrlError::BadPath));
        assert_eq!(parse_source("http://c%61m/"), Err(UrlError::BadHost("c%61m".into())));
        assert_eq!(parse_source(&format!("http://cam/{}", "a".repeat(MAX_URL_BYTES))), Err(UrlError::TooLong));
    }

    #[test]
    fn a_frame_must_be_a_whole_jpeg_of_allowed_size() {
        let good = jpeg(32, 24);
        assert_eq!(check_jpeg(&good), Ok((32, 24)));
        assert_eq!(check_jpeg(b"hello"), Err(Reject::NotJpeg("no start-of-image marker")));
        assert_eq!(check_jpeg(&good[..good.len() - 10]), Err(Reject::NotJpeg("no end-of-image marker")));
        let mut markers_only = vec![0xff, 0xd8];
        markers_only.extend_from_slice(&[0x00; 64]);
        markers_only.extend_from_slice(&[0xff, 0xd9]);
        assert!(matches!(check_jpeg(&markers_only), Err(Reject::Undecodable(_))), "{:?}", check_jpeg(&markers_only));
        let mut huge = good.clone();
        // The frame header (SOF0): height, then width, each two bytes.
        let sof = huge.windows(2).position(|w| w == [0xff, 0xc0]).unwrap();
        huge[sof + 5..sof + 9].copy_from_slice(&[0x0b, 0xb8, 0x0f, 0xa0]);
        assert_eq!(check_jpeg(&huge), Err(Reject::TooWide(4000, 3000)));
        assert_eq!(check_jpeg(&vec![0; MAX_FRAME_BYTES + 1]), Err(Reject::TooLarge(MAX_FRAME_BYTES + 1)));
    }

    fn part(boundary: &str, body: &[u8], length: bool) -> Vec<u8> {
        let mut out = format!("--{boundary}\r\nContent-Type: image/jpeg\r\n").into_bytes();
        if length {
            out.extend_from_slice(format!("Content-Length: {}\r\n", body.len()).as_bytes());
        }
        out.extend_from_slice(b"\r\n");
        out.extend_from_slice(body);
        out.extend_from_slice(b"\r\n");
        out
    }

    #[test]
    fn parts_split_with_and_without_lengths_and_bad_ones_are_rejected_not_fatal() {
        let frame = jpeg(16, 16);
        let mut stream = part("b", &frame, true);
        stream.extend(part("b", b"not a picture", true));
        stream.extend(part("b", &frame, false));
        stream.extend(part("b", &vec![7; MAX_FRAME_BYTES + 10], true));
        stream.extend(part("b", &vec![7; MAX_FRAME_BYTES + 10], false));
        stream.extend(part("b", &frame, false));
        stream.extend(b"--b--\r\n");
        // Learnt from the first line, as from ffmpeg's server.
        let mut parts = Parts::new(&stream[..], None);
        let whole = Part::Frame { jpeg: frame.clone(), width: 16, height: 16 };
        assert_eq!(parts.next_part().unwrap(), whole);
        assert_eq!(parts.next_part().unwrap(), Part::Rejected(Reject::NotJpeg("no start-of-image marker")));
        assert_eq!(parts.next_part().unwrap(), whole);
        assert_eq!(parts.next_part().unwrap(), Part::Rejected(Reject::TooLarge(MAX_FRAME_BYTES + 10)));
        assert_eq!(parts.next_part().unwrap(), Part::Rejected(Reject::TooLarge(MAX_FRAME_BYTES + 10)));
        assert_eq!(parts.next_part().unwrap(), whole);
        assert!(matches!(parts.next_part(), Err(StreamError::Ended)));
    }

    #[test]
    fn garbage_loses_the_framing() {
        let mut parts = Parts::new(&b"\x00\x01garbage garbage\n"[..], None);
        assert!(matches!(parts.next_part(), Err(StreamError::LostSync(_))));
        let long = vec![b'x'; 10 * MAX_LINE_BYTES];
        assert!(matches!(Parts::new(&long[..], None).next_part(), Err(StreamError::LostSync(_))));
        let mut other = Parts::new(&b"--a\r\n"[..], Some(b"b".to_vec()));
        assert!(matches!(other.next_part(), Err(StreamError::LostSync(_))));
    }

    #[test]
    fn a_chunked_body_is_read_through_its_chunks() {
        let frame = jpeg(16, 16);
        let stream = part("ffmpeg", &frame, true);
        let mut chunked = Vec::new();
        for piece in stream.chunks(100) {
            chunked.extend(format!("{:x}\r\n", piece.len()).into_bytes());
            chunked.extend_from_slice(piece);
            chunked.extend(b"\r\n");
        }
        chunked.extend(b"0\r\n\r\n");
        let body = Chunked { inner: &chunked[..], left: 0, done: false };
        let mut parts = Parts::new(body, Some(b"ffmpeg".to_vec()));
        assert_eq!(parts.next_part().unwrap(), Part::Frame { jpeg: frame, width: 16, height: 16 });
        assert!(matches!(parts.next_part(), Err(StreamError::Ended)));
        let bad = Chunked { inner: &b"zz\r\nabc"[..], left: 0, done: false };
        assert!(matches!(Parts::new(bad, None).next_part(), Err(StreamError::LostSync(_))));
    }

    #[test]
    fn the_boundary_comes_from_the_content_type() {
        assert_eq!(boundary_of("multipart/x-mixed-replace; boundary=\"--myb\""), Some(b"myb".to_vec()));
        assert_eq!(boundary_of("multipart/x-mixed-replace;boundary=ffmpeg"), Some(b"ffmpeg".to_vec()));
        assert_eq!(boundary_of("application/octet-stream"), None);
    }
}
