//! The compact text form of a pipeline: `crop(84)|grayscale(p=0.3)`.
//!
//! ```text
//! pipeline := "" | "none" | stage ("|" stage)*
//! stage    := name [ "(" [ arg ("," arg)* ] ")" ]
//! arg      := [ key "=" ] number          positional arguments come first, in the order listed
//! ```
//! Omitted arguments take the paper's defaults (see [`Augmentation`]).

use std::str::FromStr;

use crate::error::{AugmentError, Result};
use crate::spec::{Augmentation, Pipeline, MAX_STAGES, NAMES};

/// The longest text form accepted (far above any real pipeline: eight stages with every argument
/// named take under 400 bytes).
pub const MAX_TEXT_BYTES: usize = 1024;

/// Names longer than any augmentation's (with slack for typos) get no suggestion and are clipped
/// in the message.
const MAX_NAME_CHARS: usize = 32;

/// Parameter names of each augmentation, in positional order, with their defaults.
fn parameters(name: &str) -> &'static [(&'static str, f64)] {
    match name {
        "crop" | "window" | "center_crop" => &[("size", 84.0)],
        "translate" | "center_translate" => &[("size", 108.0)],
        "shift" => &[("pad", 4.0)],
        "intensity" => &[("scale", 0.05)],
        "grayscale" => &[("p", 0.3)],
        "flip" => &[("p", 0.2)],
        "rotate" => &[("p", 0.3)],
        "cutout" | "cutout_color" => &[("min", 10.0), ("max", 30.0)],
        "conv" => &[],
        "color_jitter" => &[("brightness", 0.4), ("contrast", 0.4), ("saturation", 0.4), ("hue", 0.5)],
        "ras_s" | "ras_m" => &[("alpha", 0.6), ("beta", 1.4)],
        "noise" => &[("std", 1.0)],
        _ => unreachable!("parameters() is only called with canonical names"),
    }
}

impl FromStr for Pipeline {
    type Err = AugmentError;

    fn from_str(text: &str) -> Result<Self> {
        Pipeline::parse(text)
    }
}

impl Pipeline {
    /// Parse the text form; every problem is reported with its position and what was expected.
    pub fn parse(text: &str) -> Result<Self> {
        if text.len() > MAX_TEXT_BYTES {
            return Err(AugmentError::TooLong {
                message: format!("a pipeline's text is at most {MAX_TEXT_BYTES} bytes, got {}", text.len()),
            });
        }
        let trimmed = text.trim();
        if trimmed.is_empty() || trimmed == "none" || trimmed == "no_aug" {
            return Ok(Self::identity());
        }
        let mut stages = Vec::new();
        let mut offset = 0;
        let count = text.split('|').count();
        if count > MAX_STAGES {
            return Err(AugmentError::TooLong { message: format!("a pipeline has at most {MAX_STAGES} stages, got {count}") });
        }
        for part in text.split('|') {
            stages.push(parse_stage(text, part, offset)?);
            offset += part.chars().count() + 1;
        }
        Self::new(stages)
    }
}

fn syntax(text: &str, at: usize, message: impl Into<String>) -> AugmentError {
    AugmentError::Syntax { text: text.to_owned(), at, message: message.into() }
}

fn parse_stage(text: &str, part: &str, offset: usize) -> Result<Augmentation> {
    let leading = part.chars().take_while(|c| c.is_whitespace()).count();
    let body = part.trim();
    let start = offset + leading;
    if body.is_empty() {
        return Err(syntax(text, start, "empty stage; expected an augmentation name such as crop(84)"));
    }
    let (raw_name, arguments) = match body.find('(') {
        None => (body, None),
        Some(open) => {
            let Some(inner) = body[open + 1..].strip_suffix(')') else {
                return Err(syntax(text, start + body.chars().count(), "expected ')' closing the argument list"));
            };
            (body[..open].trim_end(), Some((inner, start + body[..=open].chars().count())))
        }
    };
    let name = canonical_name(raw_name)?;
    let spec = parameters(name);
    let mut values: Vec<Option<f64>> = vec![None; spec.len()];
    if let Some((inner, inner_start)) = arguments {
        parse_arguments(text, name, spec, inner, inner_start, &mut values)?;
    }
    let value = |index: usize| values[index].unwrap_or(spec[index].1);
    let integer = |index: usize| -> Result<usize> {
        let number = value(index);
        if number.fract() != 0.0 || !(0.0..=1e6).contains(&number) {
            return Err(AugmentError::InvalidParameter {
                augmentation: name,
                message: format!("{} must be a whole number of pixels, got {number}", spec[index].0),
            });
        }
        Ok(number as usize)
    };
    let real = |index: usize| value(index) as f32;
    Ok(match name {
        "crop" => Augmentation::Crop { size: integer(0)? },
        "translate" => Augmentation::Translate { size: integer(0)? },
        "window" => Augmentation::Window { size: integer(0)? },
        "center_crop" => Augmentation::CenterCrop { size: integer(0)? },
        "center_translate" => Augmentation::CenterTranslate { size: integer(0)? },
        "shift" => Augmentation::Shift { pad: integer(0)? },
        "intensity" => Augmentation::Intensity { scale: real(0) },
        "grayscale" => Augmentation::Grayscale { p: real(0) },
        "flip" => Augmentation::Flip { p: real(0) },
        "rotate" => Augmentation::Rotate { p: real(0) },
        "cutout" => Augmentation::Cutout { min: integer(0)?, max: integer(1)? },
        "cutout_color" => Augmentation::CutoutColor { min: integer(0)?, max: integer(1)? },
        "conv" => Augmentation::RandomConv,
        "color_jitter" => {
            Augmentation::ColorJitter { brightness: real(0), contrast: real(1), saturation: real(2), hue: real(3) }
        }
        "ras_s" => Augmentation::AmplitudeScale { per_dimension: false, alpha: real(0), beta: real(1) },
        "ras_m" => Augmentation::AmplitudeScale { per_dimension: true, alpha: real(0), beta: real(1) },
        "noise" => Augmentation::GaussianNoise { std: real(0) },
        _ => unreachable!("canonical_name returns only names listed in NAMES"),
    })
}

fn parse_arguments(
    text: &str,
    name: &'static str,
    spec: &[(&'static str, f64)],
    inner: &str,
    inner_start: usize,
    values: &mut [Option<f64>],
) -> Result<()> {
    if inner.trim().is_empty() {
        return Ok(());
    }
    let mut position = inner_start;
    let mut seen_keyword = false;
    for (index, argument) in inner.split(',').enumerate() {
        let at = position + argument.chars().take_while(|c| c.is_whitespace()).count();
        position += argument.chars().count() + 1;
        let (slot, raw_value) = match argument.split_once('=') {
            Some((key, raw_value)) => {
                seen_keyword = true;
                let key = key.trim();
                let Some(slot) = spec.iter().position(|(parameter, _)| *parameter == key) else {
                    let accepted: Vec<_> = spec.iter().map(|(parameter, _)| *parameter).collect();
                    let accepted = if accepted.is_empty() { "none".to_owned() } else { accepted.join(", ") };
                    return Err(syntax(text, at, format!("{name} has no parameter {key:?}; it takes: {accepted}")));
                };
                (slot, raw_value)
            }
            None => {
                if seen_keyword {
                    return Err(syntax(text, at, "a positional argument cannot follow a keyword argument"));
                }
                if index >= spec.len() {
                    return Err(syntax(
                        text,
                        at,
                        format!("{name} takes at most {} argument(s), got {}", spec.len(), inner.split(',').count()),
                    ));
                }
                (index, argument)
            }
        };
        if values[slot].is_some() {
            return Err(syntax(text, at, format!("{} given twice", spec[slot].0)));
        }
        let raw_value = raw_value.trim();
        let number: f64 = raw_value
            .parse()
            .ok()
            .filter(|number: &f64| number.is_finite())
            .ok_or_else(|| syntax(text, at, format!("{} must be a number, got {raw_value:?}", spec[slot].0)))?;
        values[slot] = Some(number);
    }
    Ok(())
}

fn canonical_name(raw: &str) -> Result<&'static str> {
    let lowered = raw.to_ascii_lowercase().replace('-', "_");
    for (canonical, aliases) in NAMES {
        if *canonical == lowered || aliases.contains(&lowered.as_str()) {
            return Ok(canonical);
        }
    }
    if raw.chars().count() > MAX_NAME_CHARS {
        let clipped: String = raw.chars().take(MAX_NAME_CHARS).collect();
        return Err(AugmentError::UnknownAugmentation {
            name: format!("{clipped}..."),
            suggestion: String::new(),
            expected: NAMES.iter().map(|(canonical, _)| *canonical).collect::<Vec<_>>().join(", "),
        });
    }
    let closest = NAMES
        .iter()
        .map(|(canonical, _)| (strsim::levenshtein(&lowered, canonical), *canonical))
        .min()
        .filter(|(distance, _)| *distance <= 2);
    Err(AugmentError::UnknownAugmentation {
        name: raw.to_owned(),
        suggestion: closest.map(|(_, name)| format!(" (did you mean {name:?}?)")).unwrap_or_default(),
        expected: NAMES.iter().map(|(canonical, _)| *canonical).collect::<Vec<_>>().join(", "),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_follow_the_paper() {
        let pipeline = Pipeline::parse("crop|translate|grayscale|cutout|flip|rotate|conv|color_jitter").unwrap();
        assert_eq!(
            pipeline.stages(),
            &[
                Augmentation::Crop { size: 84 },
                Augmentation::Translate { size: 108 },
                Augmentation::Grayscale { p: 0.3 },
                Augmentation::Cutout { min: 10, max: 30 },
                Augmentation::Flip { p: 0.2 },
                Augmentation::Rotate { p: 0.3 },
                Augmentation::RandomConv,
                Augmentation::ColorJitter { brightness: 0.4, contrast: 0.4, saturation: 0.4, hue: 0.5 },
            ]
        );
        // DrQ's and DrQ-v2's: a 4-pixel shift, intensity 0.05 (DrQ on Atari, SPR).
        let drq = Pipeline::parse("shift|intensity|random_shift(2)").unwrap();
        assert_eq!(
            drq.stages(),
            &[Augmentation::Shift { pad: 4 }, Augmentation::Intensity { scale: 0.05 }, Augmentation::Shift { pad: 2 }]
        );
        assert!(Pipeline::parse("shift(0)").unwrap_err().to_string().contains("pad must be at least 1"));
        assert!(Pipeline::parse("intensity(0.6)").unwrap_err().to_string().contains("scale must be in [0, 0.5]"));
    }

    #[test]
    fn positional_keyword_whitespace_and_aliases() {
        let pipeline = Pipeline::parse(" crop( 64 ) | gray(p = 1) |rand_conv| cutout(5, max=7) | ras_m(0.5,1.5)").unwrap();
        assert_eq!(
            pipeline.stages(),
            &[
                Augmentation::Crop { size: 64 },
                Augmentation::Grayscale { p: 1.0 },
                Augmentation::RandomConv,
                Augmentation::Cutout { min: 5, max: 7 },
                Augmentation::AmplitudeScale { per_dimension: true, alpha: 0.5, beta: 1.5 },
            ]
        );
    }

    #[test]
    fn display_round_trips() {
        for text in ["crop(84)|grayscale(p=0.3)", "translate(108)", "cutout_color(min=3,max=9)|flip(p=0.5)", "conv", "none", "shift(4)|intensity(scale=0.05)",
            "color_jitter(brightness=0.2,contrast=0.3,saturation=0.4,hue=0.1)", "ras_s(alpha=0.6,beta=1.4)|noise(std=0.5)"]
        {
            let pipeline = Pipeline::parse(text).unwrap();
            assert_eq!(pipeline.to_string(), text);
            assert_eq!(Pipeline::parse(&pipeline.to_string()).unwrap(), pipeline);
        }
        assert!(Pipeline::parse("").unwrap().is_empty());
        assert!(Pipeline::parse("no_aug").unwrap().is_empty());
    }

    #[test]
    fn nonsense_is_rejected_with_what_was_expected() {
        let message = |text: &str| Pipeline::parse(text).unwrap_err().to_string();
        assert!(message("crpo(84)").contains("did you mean \"crop\""), "{}", message("crpo(84)"));
        assert!(message("sharpen").contains("expected one of: crop, translate"));
        assert!(message("grayscale(p=1.5)").contains("p must be a probability in [0, 1], got 1.5"));
        assert!(message("crop(0)").contains("size must be at least 1"));
        assert!(message("crop(84.5)").contains("whole number"));
        assert!(message("crop(-3)").contains("whole number"));
        assert!(message("crop(84").contains("expected ')'"));
        assert!(message("crop(size=84, size=90)").contains("size given twice"));
        assert!(message("crop(84, 3)").contains("at most 1 argument"));
        assert!(message("flip(q=0.1)").contains("flip has no parameter \"q\"; it takes: p"));
        assert!(message("conv(3)").contains("at most 0 argument"));
        assert!(message("cutout(max=4, 9)").contains("positional argument cannot follow"));
        assert!(message("cutout(20, 10)").contains("min must not exceed max"));
        assert!(message("crop|").contains("empty stage"));
        assert!(message("flip(p=nan)").contains("must be a number"));
        assert!(message("color_jitter(hue=0.7)").contains("hue must be in [0, 0.5]"));
        assert!(message("ras_s(1.4, 0.6)").contains("alpha <= beta"));
        assert!(message("noise(std=-1)").contains("non-negative"));
    }

    #[test]
    fn syntax_errors_point_at_the_stage() {
        let Err(AugmentError::Syntax { at, .. }) = Pipeline::parse("crop(84)|  flip(q=1)") else { panic!() };
        assert_eq!(at, 16);
    }
}
