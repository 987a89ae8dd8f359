//! Numbers as people type them on the command line and the simulator's console:
//! decimal, `0x` hex or `0b` binary, with an optional minus sign.

/// `123`, `0x7B`, `0b1111011`, `-5`; `None` for anything else.
pub(crate) fn parse(s: &str) -> Option<i64> {
    let (negative, digits) = match s.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, s),
    };
    let (radix, digits) = if let Some(h) = digits
        .strip_prefix("0x")
        .or_else(|| digits.strip_prefix("0X"))
    {
        (16, h)
    } else if let Some(b) = digits
        .strip_prefix("0b")
        .or_else(|| digits.strip_prefix("0B"))
    {
        (2, b)
    } else {
        (10, digits)
    };
    // from_str_radix accepts a sign of its own: refuse a second one.
    if digits.is_empty() || !digits.chars().all(|c| c.is_digit(radix)) {
        return None;
    }
    let v = i64::from_str_radix(digits, radix).ok()?;
    Some(if negative { -v } else { v })
}

#[cfg(test)]
mod tests {
    use super::parse;

    #[test]
    fn forms() {
        assert_eq!(parse("123"), Some(123));
        assert_eq!(parse("0x7B"), Some(123));
        assert_eq!(parse("0X7b"), Some(123));
        assert_eq!(parse("0b1111011"), Some(123));
        assert_eq!(parse("-32768"), Some(-32768));
        assert_eq!(parse("-0x10"), Some(-16));
        for bad in ["", "-", "0x", "+5", "--5", "0x-5", "12a", "0b12", " 1"] {
            assert_eq!(parse(bad), None, "{bad:?}");
        }
    }
}
