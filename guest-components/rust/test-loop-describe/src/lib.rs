//! Test guest that never finishes `describe`: loading it must fail with a
//! time-budget error instead of hanging the host.

use subsume_guest::{Component, Description, Params};

struct Stuck;

impl Component for Stuck {
    fn describe() -> Description {
        let mut spins: u64 = 0;
        loop {
            spins = std::hint::black_box(spins.wrapping_add(1));
        }
    }
    fn init(_params: &Params) -> Result<Self, String> {
        Ok(Stuck)
    }
}

subsume_guest::component!(Stuck);
