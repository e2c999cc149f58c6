//! Bounds on every request field that carries text or a count, checked before any work is done with
//! it, and the clipping of request text echoed back in error messages.
//!
//! An error message travels in the `grpc-message` trailer, whose size clients cap (grpcio: 8 KiB of
//! metadata); an unbounded echo would turn the real error into "metadata size exceeds hard limit".

use crate::error::CoreError;

/// Environment ids, session ids and ListEnvs prefixes (the longest real id is under 40 bytes).
pub const MAX_ID_BYTES: usize = 256;
/// Options in one CreateSession (the largest family schema has 12).
pub const MAX_OPTIONS: usize = 32;
/// An option's name (the longest is under 25 bytes).
pub const MAX_OPTION_NAME_BYTES: usize = 64;
/// A string option's value (the longest accepted value is under 15 bytes).
pub const MAX_OPTION_TEXT_BYTES: usize = 256;
/// Request text quoted in an error message.
pub const ECHO_CHARS: usize = 64;

/// `text` as it may appear in an error message: at most [`ECHO_CHARS`] characters, with the length
/// of what was left out.
pub fn clip(text: &str) -> String {
    match text.char_indices().nth(ECHO_CHARS) {
        None => text.to_string(),
        Some((end, _)) => format!("{}... ({} bytes in all)", &text[..end], text.len()),
    }
}

/// Refuses `value` of request field `field` when it is longer than `max` bytes, without echoing it.
pub fn check_len(field: &str, value: &str, max: usize) -> Result<(), CoreError> {
    if value.len() > max {
        return Err(CoreError::OutOfBounds(format!(
            "{field} is {} bytes long; the most accepted is {max}",
            value.len()
        )));
    }
    Ok(())
}

/// Refuses a request that lists more than `max` items in `field`.
pub fn check_count(field: &str, count: usize, max: usize) -> Result<(), CoreError> {
    if count > max {
        return Err(CoreError::OutOfBounds(format!("{field} has {count} entries; the most accepted is {max}")));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_text_is_clipped_on_a_character_boundary() {
        assert_eq!(clip("dmc/cheetah-run"), "dmc/cheetah-run");
        let long = "é".repeat(100_000);
        let clipped = clip(&long);
        assert!(clipped.starts_with(&"é".repeat(ECHO_CHARS)));
        assert!(clipped.ends_with("(200000 bytes in all)"), "{clipped}");
        assert!(clipped.len() < 200);
    }

    #[test]
    fn lengths_and_counts_are_refused_without_echo() {
        let error = check_len("env_id", &"x".repeat(1000), MAX_ID_BYTES).unwrap_err().to_string();
        assert_eq!(error, "env_id is 1000 bytes long; the most accepted is 256");
        assert!(check_len("env_id", "gym/CartPole-v1", MAX_ID_BYTES).is_ok());
        assert!(check_count("options", 33, MAX_OPTIONS).is_err());
        assert!(check_count("options", 32, MAX_OPTIONS).is_ok());
    }
}
