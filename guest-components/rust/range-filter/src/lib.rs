//! Range-sensor filter: cleans a range scan before the behaviours see it.
//!
//! Invalid readings (NaN, negative, infinite) and readings past `max-range`
//! become `max-range`; each ray is then smoothed with an exponential moving
//! average (`alpha` = weight of the newest reading). Emits the filtered scan and
//! the nearest reading every time a scan arrives (input is passive).

use subsume_guest::{Component, Description, ParamKind, Params, Value, ValueKind, emit, input, output, param};

struct RangeFilter {
    alpha: f64,
    max_range: f64,
    smoothed: Vec<f64>,
}

impl Component for RangeFilter {
    fn describe() -> Description {
        Description::new("range-filter", "Clamps and smooths a range scan")
            .input(input("ranges", ValueKind::Vector, "raw ranges in metres, one per ray"))
            .output(output("filtered", ValueKind::Vector, "clamped, smoothed ranges in metres"))
            .output(output("nearest", ValueKind::Scalar, "smallest filtered range in metres"))
            .param(param("alpha", ParamKind::Number, "0.6", "weight of the newest reading, 0 < alpha <= 1"))
            .param(param("max-range", ParamKind::Number, "4.0", "sensor range in metres; invalid readings become this"))
    }

    fn init(params: &Params) -> Result<Self, String> {
        let alpha = params.number("alpha")?;
        let max_range = params.number("max-range")?;
        if !(alpha > 0.0 && alpha <= 1.0) {
            return Err(format!("alpha must be in (0, 1], got {alpha}"));
        }
        if !(max_range > 0.0 && max_range.is_finite()) {
            return Err(format!("max-range must be a positive number, got {max_range}"));
        }
        Ok(RangeFilter { alpha, max_range, smoothed: Vec::new() })
    }

    fn on_input(&mut self, _port: u32, value: Value) -> Result<(), String> {
        let Value::Vector(raw) = value else {
            return Err("ranges: expected a vector".into());
        };
        if raw.len() != self.smoothed.len() {
            // First scan, or the sensor changed its ray count: start afresh.
            self.smoothed = raw.iter().map(|&r| self.clamp(r)).collect();
        } else {
            for (s, &r) in self.smoothed.iter_mut().zip(&raw) {
                let r = if r.is_finite() && r >= 0.0 { r.min(self.max_range) } else { self.max_range };
                *s += self.alpha * (r - *s);
            }
        }
        let nearest = self.smoothed.iter().copied().fold(self.max_range, f64::min);
        emit(0, &Value::Vector(self.smoothed.clone()));
        emit(1, &Value::Scalar(nearest));
        Ok(())
    }
}

impl RangeFilter {
    fn clamp(&self, r: f64) -> f64 {
        if r.is_finite() && r >= 0.0 { r.min(self.max_range) } else { self.max_range }
    }
}

subsume_guest::component!(RangeFilter);
