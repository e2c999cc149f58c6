//! Quick table of every kernel vs a parallel copy: `cargo run --release -p radserve-augment --example speed`.
use radserve_augment::{speed, FrameShape, Pipeline};

fn main() {
    let filter = std::env::args().nth(1).unwrap_or_default();
    let batch = 512;
    for (text, side) in [
        ("crop(84)", 100), ("translate(108)", 100), ("window(84)", 100), ("center_crop(84)", 100),
        ("flip(p=1)", 84), ("rotate(p=1)", 84), ("cutout", 84), ("cutout_color", 84),
        ("grayscale(p=1)", 84), ("conv", 84), ("color_jitter", 84),
    ] {
        if !text.contains(&filter) { continue; }
        let shape = FrameShape::new(3, 3, side, side);
        let input: Vec<u8> = (0..batch * shape.sample_len()).map(|i| (i * 7919 % 251) as u8).collect();
        let m = speed::measure(&Pipeline::parse(text).unwrap(), shape, &input, 15).unwrap();
        println!("{:<16} {:>8.2} ms  {:>6.2} GB/s  copy {:>6.2} ms  ratio {:>5.2}", text, m.seconds * 1e3, m.gigabytes_per_second(), m.copy_seconds * 1e3, m.ratio_to_copy());
    }
}
