//! Opening the serial device: raw 8N1 at the link's baud rate, reads
//! bounded by a timeout.
//!
//! `serialport` sets the line with Linux's `termios2` ioctls (`TCGETS2`,
//! `TCSETS2`), which allow any baud rate. Some environments do not
//! implement them: qemu-user 7.2 (Debian bookworm's, used to smoke-test the
//! aarch64 build) answers `ENOTTY`, so no device would ever open there. When
//! that open fails, the classic termios calls (`tcsetattr` with a standard
//! `Bnnn` rate) are tried; a rate the classic calls cannot express keeps the
//! first error.

use std::fs::OpenOptions;
use std::io;
use std::os::fd::{AsRawFd, FromRawFd, IntoRawFd};
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::time::Duration;

use serialport::{SerialPort, TTYPort};

/// Opens `device` raw at `baud`, reads waiting at most `timeout`.
pub fn open(device: &Path, baud: u32, timeout: Duration) -> Result<TTYPort, serialport::Error> {
    match serialport::new(device.to_string_lossy(), baud).timeout(timeout).open_native() {
        Ok(port) => Ok(port),
        Err(first) => match open_classic(device, baud, timeout) {
            Ok(port) => {
                tracing::debug!("{}: opened with classic termios ({first})", device.display());
                Ok(port)
            }
            Err(_) => Err(first),
        },
    }
}

/// The classic termios constant for `baud`, if it has one.
pub fn classic_speed(baud: u32) -> Option<libc::speed_t> {
    Some(match baud {
        1200 => libc::B1200,
        2400 => libc::B2400,
        4800 => libc::B4800,
        9600 => libc::B9600,
        19200 => libc::B19200,
        38400 => libc::B38400,
        57600 => libc::B57600,
        115200 => libc::B115200,
        230400 => libc::B230400,
        460800 => libc::B460800,
        500000 => libc::B500000,
        921600 => libc::B921600,
        1000000 => libc::B1000000,
        2000000 => libc::B2000000,
        _ => return None,
    })
}

/// Opens `device` with `open(2)` and the classic termios calls only.
pub fn open_classic(device: &Path, baud: u32, timeout: Duration) -> io::Result<TTYPort> {
    let speed = classic_speed(baud)
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, format!("{baud} baud is not a standard rate")))?;
    let file = OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NOCTTY | libc::O_NONBLOCK | libc::O_CLOEXEC)
        .open(device)?;
    let fd = file.as_raw_fd();
    // SAFETY: `fd` is open for the whole block (owned by `file`), and
    // `termios` is a plain C struct that tcgetattr fills before it is read.
    unsafe {
        let mut termios: libc::termios = std::mem::zeroed();
        check(libc::tcgetattr(fd, &mut termios))?;
        libc::cfmakeraw(&mut termios);
        termios.c_cflag |= libc::CREAD | libc::CLOCAL;
        termios.c_cflag &= !(libc::CSTOPB | libc::PARENB | libc::CRTSCTS);
        termios.c_iflag &= !(libc::IXON | libc::IXOFF | libc::IXANY);
        check(libc::cfsetispeed(&mut termios, speed))?;
        check(libc::cfsetospeed(&mut termios, speed))?;
        check(libc::tcsetattr(fd, libc::TCSANOW, &termios))?;
        // Blocking again: reads wait in poll(2) with the port's timeout.
        check(libc::fcntl(fd, libc::F_SETFL, 0))?;
    }
    // SAFETY: the descriptor is open and owned by nobody else once
    // `into_raw_fd` hands it over; TTYPort closes it when dropped.
    let mut port = unsafe { TTYPort::from_raw_fd(file.into_raw_fd()) };
    port.set_timeout(timeout).map_err(io::Error::from)?;
    Ok(port)
}

fn check(rc: libc::c_int) -> io::Result<()> {
    if rc < 0 { Err(io::Error::last_os_error()) } else { Ok(()) }
}

#[cfg(test)]
mod tests {
    use std::io::{Read, Write};

    use super::*;

    #[test]
    fn the_classic_open_moves_bytes_both_ways_on_a_pty_at_a_standard_rate() {
        let (mut master, slave) = TTYPort::pair().unwrap();
        let name = slave.name().unwrap();
        drop(slave);
        let mut port = open_classic(Path::new(&name), 115200, Duration::from_millis(500)).unwrap();
        // Raw: no echo, no line discipline, bytes pass unchanged (0x03 is
        // not an interrupt, \r is not translated).
        port.write_all(&[0x80, 0x83, 0x03, b'\r', 0x00]).unwrap();
        let mut got = [0u8; 5];
        master.read_exact(&mut got).unwrap();
        assert_eq!(got, [0x80, 0x83, 0x03, b'\r', 0x00]);
        master.write_all(b"\x13\x11ok\r").unwrap();
        let mut back = [0u8; 5];
        port.read_exact(&mut back).unwrap();
        assert_eq!(&back, b"\x13\x11ok\r");
        // Reads wait no longer than the timeout.
        let mut one = [0u8; 1];
        assert!(port.read(&mut one).is_err());
    }

    #[test]
    fn a_rate_classic_termios_cannot_express_is_refused_by_name() {
        let err = open_classic(Path::new("/dev/null"), 123_456, Duration::from_millis(10)).unwrap_err();
        assert!(err.to_string().contains("123456 baud is not a standard rate"), "{err}");
        assert_eq!(classic_speed(115200), Some(libc::B115200));
    }
}
