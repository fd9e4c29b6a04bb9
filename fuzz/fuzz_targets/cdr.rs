//! ROS 2 CDR payloads from the network (the ROS 2 face): every decoder
//! takes any bytes without panicking or allocating past its limits, and a
//! message it decodes encodes to bytes that decode to the same message.
#![no_main]
// The codec module is shared with the host; not every item is used here.
#![allow(dead_code)]

#[path = "../../host/src/bridge/cdr.rs"]
mod cdr;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Ok(t) = cdr::Twist::decode(data) {
        assert_eq!(cdr::Twist::decode(&t.encode()), Ok(t));
    }
    if let Ok(o) = cdr::Odometry::decode(data) {
        assert_eq!(
            cdr::Odometry::decode(&o.encode()).map(|b| (b.position, b.orientation)),
            Ok((o.position, o.orientation))
        );
    }
    if let Ok(s) = cdr::LaserScan::decode(data) {
        assert!(s.ranges.len() <= cdr::MAX_SEQUENCE_LEN);
        let again = cdr::LaserScan::decode(&s.encode()).map(|b| b.ranges.len());
        assert_eq!(again, Ok(s.ranges.len()));
    }
    if let Ok(l) = cdr::Log::decode(data) {
        assert_eq!(cdr::Log::decode(&l.encode()), Ok(l));
    }
    let _ = cdr::decode_bool(data);
});
