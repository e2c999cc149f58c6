//! `radserve augment-bench` and `radserve augment-preview`: the augmentation engine from the
//! command line, for measuring it and for looking at what every augmentation does.

use std::path::Path;

use anyhow::{bail, Context};
use radserve_augment::speed::{self, noise, Measurement, PAPER_CASES};
use radserve_augment::{Draws, FrameShape, ImagePlan, Pipeline};
use radserve_core::{DType, OptionValue, Options, SessionExtras, SessionManager, Space};

/// Time every case at `batch` samples on `threads` threads (0: one per core) and print a table,
/// or one JSON object per line.
pub fn bench(batch: usize, repeats: usize, threads: usize, filter: &str, json: bool) -> anyhow::Result<()> {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().context("building the thread pool")?;
    if !json {
        println!(
            "{:<28} {:>18} {:>10} {:>8} {:>10} {:>9}",
            "pipeline", "output", "ms/batch", "GB/s", "copy ms", "x copy"
        );
    }
    for (text, side) in PAPER_CASES.iter().filter(|(text, _)| text.contains(filter)) {
        let pipeline = Pipeline::parse(text)?;
        let shape = FrameShape::new(3, 3, *side, *side);
        let input = noise(batch * shape.sample_len(), *side as u64);
        let measurement: Measurement = pool.install(|| speed::measure(&pipeline, shape, &input, repeats))?;
        let output = measurement.output;
        if json {
            println!(
                "{{\"pipeline\":\"{}\",\"batch\":{},\"input\":[{},{},{}],\"output\":[{},{},{}],\"output_bytes\":{},\"seconds\":{},\"copy_seconds\":{},\"threads\":{}}}",
                measurement.pipeline, batch, shape.planes(), shape.height, shape.width, output.planes(), output.height,
                output.width, measurement.output_bytes, measurement.seconds, measurement.copy_seconds, pool.current_num_threads()
            );
        } else {
            println!(
                "{:<28} {:>18} {:>10.2} {:>8.2} {:>10.2} {:>9.2}",
                text,
                format!("{batch}x{}x{}x{}", output.planes(), output.height, output.width),
                measurement.seconds * 1e3,
                measurement.gigabytes_per_second(),
                measurement.copy_seconds * 1e3,
                measurement.ratio_to_copy()
            );
        }
    }
    Ok(())
}

/// The preview's rows for a square frame of `side` pixels, sizes scaled like the paper's 84/100.
fn preview_pipelines(side: usize) -> Vec<String> {
    let scaled = |fraction: f64| ((side as f64 * fraction).round() as usize).max(1);
    let cut_max = (side * 3 / 10).max(1);
    let cut_min = (side / 10).clamp(1, cut_max);
    vec![
        "none".into(),
        format!("crop({})", scaled(0.84)),
        format!("translate({})", scaled(1.08)),
        format!("window({})", scaled(0.84)),
        "grayscale(p=1)".into(),
        format!("cutout({cut_min},{cut_max})"),
        format!("cutout_color({cut_min},{cut_max})"),
        "flip(p=1)".into(),
        "rotate(p=1)".into(),
        "conv".into(),
        "color_jitter".into(),
        format!("center_crop({})", scaled(0.84)),
        format!("center_translate({})", scaled(1.08)),
        format!("shift({})", scaled(4.0 / 84.0)),
        "intensity".into(),
    ]
}

/// One frame `[3, side, side]` from a fresh episode of `env` (seeded), through the simulators.
async fn render_frame(manager: &SessionManager, env: &str, seed: u64) -> anyhow::Result<(Vec<u8>, usize)> {
    let mut overrides = Options::new();
    overrides.insert("frame_stack".into(), OptionValue::Int(1));
    let info = manager.create_session(&radserve_core::Principal::local(), env, 1, seed, &overrides, &SessionExtras::default()).await?;
    let Space::Box { dtype: DType::Uint8, shape, .. } = &info.observation_space else {
        bail!("{env} does not observe images ({}); pick a pixel environment", info.observation_space.describe());
    };
    let [3, height, width] = shape[..] else { bail!("{env} observes {shape:?}, expected [3, H, W] RGB frames") };
    if height != width {
        bail!("{env} renders {height}x{width}; the preview needs square frames");
    }
    let session = manager.get(&radserve_core::Principal::local(), &info.session_id)?;
    let frame = session.lock().await.reset(None).await?;
    manager.close_session(&radserve_core::Principal::local(), &info.session_id).await?;
    Ok((frame, width))
}

/// Write a PNG grid: one row per augmentation, `columns` independent draws across.
pub async fn preview(manager: &SessionManager, env: &str, seed: u64, columns: usize, out: &Path) -> anyhow::Result<()> {
    let (frame, side) = render_frame(manager, env, seed).await?;
    let shape = FrameShape::new(1, 3, side, side);
    let pipelines = preview_pipelines(side);
    let tile = (side as f64 * 1.08).round() as usize;
    let gutter = 4;
    let (grid_width, grid_height) = (columns * (tile + gutter) + gutter, pipelines.len() * (tile + gutter) + gutter);
    let mut grid = vec![96u8; grid_width * grid_height * 3];
    let batch = frame.repeat(columns);
    for (row, text) in pipelines.iter().enumerate() {
        let plan = ImagePlan::new(&Pipeline::parse(text)?, shape)?;
        let output_shape = plan.output_shape();
        let mut augmented = vec![0u8; columns * output_shape.sample_len()];
        plan.apply(&batch, &mut augmented, &Draws::new(seed))?;
        for (column, sample) in augmented.chunks_exact(output_shape.sample_len()).enumerate() {
            // Centre the tile in its cell; channel-first to interleaved RGB.
            let top = gutter + row * (tile + gutter) + (tile - output_shape.height) / 2;
            let left = gutter + column * (tile + gutter) + (tile - output_shape.width) / 2;
            let plane = output_shape.plane_len();
            for y in 0..output_shape.height {
                for x in 0..output_shape.width {
                    let pixel = ((top + y) * grid_width + left + x) * 3;
                    for channel in 0..3 {
                        grid[pixel + channel] = sample[channel * plane + y * output_shape.width + x];
                    }
                }
            }
        }
        println!("row {row:>2}: {}", plan.stages().first().map_or("original".to_string(), |stage| stage.to_string()));
    }
    let file = std::fs::File::create(out).with_context(|| format!("creating {}", out.display()))?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), grid_width as u32, grid_height as u32);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.write_header()?.write_image_data(&grid)?;
    println!("wrote {} ({} rows of {columns} draws, {env} seed {seed})", out.display(), pipelines.len());
    Ok(())
}
