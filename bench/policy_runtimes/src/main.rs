//! Times one model under tract and under ONNX Runtime: for each batch size, the model is prepared
//! once (tract: typed and optimized for that batch; ONNX Runtime: a session with N intra-op threads),
//! run a few times to warm up, then as many times as fit in `--seconds`; prints one JSON line per
//! (runtime, threads, batch) with the median of `--rounds` rounds, in milliseconds per call.
//!
//! usage: policy-runtimes MODEL ONNXRUNTIME_LIBRARY --batches 1,8,16 --seconds 2 --rounds 3

use std::time::Instant;

use ort::session::Session;
use tract_onnx::prelude::*;

fn arg(args: &[String], name: &str, default: &str) -> String {
    args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).cloned().unwrap_or_else(|| default.to_string())
}

fn time_calls(seconds: f64, rounds: usize, mut call: impl FnMut()) -> Vec<f64> {
    for _ in 0..3 {
        call();
    }
    (0..rounds)
        .map(|_| {
            let started = Instant::now();
            let mut calls = 0u64;
            while started.elapsed().as_secs_f64() < seconds {
                call();
                calls += 1;
            }
            started.elapsed().as_secs_f64() * 1e3 / calls as f64
        })
        .collect()
}

fn main() -> TractResult<()> {
    let args: Vec<String> = std::env::args().collect();
    let (model_path, library) = (&args[1], &args[2]);
    let batches: Vec<usize> = arg(&args, "--batches", "1,8,16").split(',').map(|b| b.parse().unwrap()).collect();
    let seconds: f64 = arg(&args, "--seconds", "2").parse().unwrap();
    let rounds: usize = arg(&args, "--rounds", "3").parse().unwrap();
    let shape: Vec<usize> = arg(&args, "--obs", "9,84,84").split(',').map(|d| d.parse().unwrap()).collect();
    let bytes = std::fs::read(model_path)?;
    let environment = ort::init_from(library).map_err(|e| anyhow::anyhow!("{e}"))?.build().map_err(|e| anyhow::anyhow!("{e}"))?;
    for &batch in &batches {
        let dims: Vec<usize> = std::iter::once(batch).chain(shape.iter().copied()).collect();
        let count: usize = dims.iter().product();
        let obs: Vec<u8> = (0..count).map(|i| (i * 7 % 251) as u8).collect();
        let report = |runtime: &str, threads: usize, times: Vec<f64>| {
            let mut sorted = times.clone();
            sorted.sort_by(f64::total_cmp);
            println!(
                "{{\"runtime\": \"{runtime}\", \"threads\": {threads}, \"batch\": {batch}, \"ms_per_call\": {:.4}, \"low\": {:.4}, \"high\": {:.4}}}",
                sorted[sorted.len() / 2],
                sorted[0],
                sorted[sorted.len() - 1]
            );
        };
        // tract: the model's input is uint8 [batch, *obs] (the RAD actor casts and divides itself).
        let model = tract_onnx::onnx()
            .model_for_read(&mut bytes.as_slice())?
            .with_input_fact(0, u8::fact(dims.clone()).into())?
            .into_optimized()?
            .into_runnable()?;
        let input: Tensor = tract_ndarray::ArrayD::from_shape_vec(dims.clone(), obs.clone())?.into();
        report("tract", 1, time_calls(seconds, rounds, || {
            model.run(tvec!(input.clone().into())).unwrap();
        }));
        for threads in [1usize, 2] {
            let error = |e: String| anyhow::anyhow!(e);
            let mut session = Session::builder(&environment)
                .map_err(|e| error(e.to_string()))?
                .with_intra_threads(threads)
                .map_err(|e| error(e.to_string()))?
                .with_intra_op_spinning(false)
                .map_err(|e| error(e.to_string()))?
                .commit_from_memory(&bytes)
                .map_err(|e| error(e.to_string()))?;
            let shape_i64: Vec<i64> = dims.iter().map(|&d| d as i64).collect();
            report("onnxruntime", threads, time_calls(seconds, rounds, || {
                let tensor = ort::value::Tensor::from_array((shape_i64.clone(), obs.clone())).unwrap();
                session.run(ort::inputs![tensor]).unwrap();
            }));
        }
    }
    Ok(())
}
