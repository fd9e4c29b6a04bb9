//! A vision example (docs/camera.md, A vision component): reads a camera's
//! `frame` (a JPEG file, `builtin:camera`'s output), decodes it with
//! `zune-jpeg`, and says how bright the picture is and where a coloured
//! marker is in it (by default the simulator camera's robot blue).
//!
//! Outputs, once per frame: `brightness` (the mean of the pixels' luma,
//! 0..255) and `marker` (`[x, y, pixels]`: the centre in pixels, x to the
//! right and y down from the top left corner, of the pixels within
//! `tolerance` of `marker-colour` in each channel, and how many there are;
//! `[-1, -1, 0]` when there are none).

use subsume_guest::{Component, Description, ParamKind, Params, Value, ValueKind, emit, input, output, param};
use zune_jpeg::JpegDecoder;
use zune_jpeg::zune_core::colorspace::ColorSpace;
use zune_jpeg::zune_core::options::DecoderOptions;

/// Largest picture decoded (pixels): a bigger frame is refused, not
/// decoded into memory the component does not have.
const MAX_PIXELS: usize = 1920 * 1080;

struct VisionMarker {
    colour: [u8; 3],
    tolerance: u8,
}

impl Component for VisionMarker {
    fn describe() -> Description {
        Description::new("vision-marker", "Mean brightness of a camera's JPEG frames and where a coloured marker is")
            .input(input("frame", ValueKind::Bytes, "a JPEG picture (builtin:camera's frame)"))
            .output(output("brightness", ValueKind::Scalar, "mean luma of the picture, 0..255"))
            .output(output(
                "marker",
                ValueKind::Vector,
                "[x, y, pixels]: the marker's centre in pixels, or [-1, -1, 0]",
            ))
            .param(param("marker-colour", ParamKind::Text, "30,90,220", "the marker's colour, R,G,B (0..255 each)"))
            .param(param("tolerance", ParamKind::Integer, "45", "how far a pixel may stray from it, per channel"))
    }

    fn init(params: &Params) -> Result<Self, String> {
        let text = params.text("marker-colour").ok_or("missing parameter 'marker-colour'")?;
        let parts: Vec<u8> = text
            .split(',')
            .map(|p| p.trim().parse::<u8>())
            .collect::<Result<_, _>>()
            .map_err(|e| format!("marker-colour must be R,G,B with each 0..255, got '{text}': {e}"))?;
        let colour: [u8; 3] =
            parts.try_into().map_err(|_| format!("marker-colour must be three numbers R,G,B, got '{text}'"))?;
        let tolerance = params.integer("tolerance")?;
        let tolerance = u8::try_from(tolerance).map_err(|_| format!("tolerance must be 0..255, got {tolerance}"))?;
        Ok(VisionMarker { colour, tolerance })
    }

    fn on_input(&mut self, _port: u32, value: Value) -> Result<(), String> {
        let Value::Bytes(jpeg) = value else {
            return Err("frame: expected bytes (a JPEG file)".into());
        };
        let options =
            DecoderOptions::default().jpeg_set_out_colorspace(ColorSpace::RGB).set_max_width(4096).set_max_height(4096);
        let mut decoder = JpegDecoder::new_with_options(&jpeg, options);
        decoder.decode_headers().map_err(|e| format!("frame: not a JPEG: {e:?}"))?;
        let (width, height) = decoder.dimensions().ok_or("frame: no size")?;
        if width * height > MAX_PIXELS {
            return Err(format!("frame: {width}x{height} is more than {MAX_PIXELS} pixels"));
        }
        let rgb = decoder.decode().map_err(|e| format!("frame: cannot decode: {e:?}"))?;
        if rgb.len() < width * height * 3 || width * height == 0 {
            return Err(format!("frame: {} bytes for {width}x{height}", rgb.len()));
        }
        let mut luma: u64 = 0;
        let (mut xs, mut ys, mut n): (u64, u64, u64) = (0, 0, 0);
        for (i, pixel) in rgb.chunks_exact(3).take(width * height).enumerate() {
            // BT.601 luma in integers: the same on every machine.
            luma += (299 * u64::from(pixel[0]) + 587 * u64::from(pixel[1]) + 114 * u64::from(pixel[2])) / 1000;
            if pixel.iter().zip(self.colour).all(|(&p, c)| p.abs_diff(c) < self.tolerance) {
                xs += (i % width) as u64;
                ys += (i / width) as u64;
                n += 1;
            }
        }
        let pixels = (width * height) as f64;
        emit(0, &Value::Scalar(luma as f64 / pixels));
        let marker = if n == 0 {
            vec![-1.0, -1.0, 0.0]
        } else {
            // Pixel centres: pixel (0, 0) covers 0..1.
            vec![xs as f64 / n as f64 + 0.5, ys as f64 / n as f64 + 0.5, n as f64]
        };
        emit(1, &Value::Vector(marker));
        Ok(())
    }
}

subsume_guest::component!(VisionMarker);
