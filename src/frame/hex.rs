//! Hex dumps for traffic logs and error messages.

use std::fmt;

/// Displays bytes as `00 01 FF`, the way docs/protocol.md writes frames.
pub struct Hex<'a>(pub &'a [u8]);

impl fmt::Display for Hex<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, b) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str(" ")?;
            }
            write!(f, "{b:02X}")?;
        }
        Ok(())
    }
}

impl fmt::Debug for Hex<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Display::fmt(self, f)
    }
}

/// `"00 01 FF"` → bytes, for tests written the way docs/protocol.md writes frames.
#[cfg(test)]
pub(crate) fn parse(s: &str) -> Vec<u8> {
    s.split_whitespace()
        .map(|h| u8::from_str_radix(h, 16).expect("hex byte"))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::Hex;

    #[test]
    fn formats_like_the_spec() {
        assert_eq!(Hex(&[0x00, 0x01, 0xFF]).to_string(), "00 01 FF");
        assert_eq!(Hex(&[]).to_string(), "");
    }
}
