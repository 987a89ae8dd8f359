//! Tests of tools::wire.

use super::*;

#[test]
fn end_specs_parse() {
    let s: EndSpec = "9600,8E1".parse().unwrap();
    assert_eq!(s.baud, Some(9600));
    assert_eq!(s.format.unwrap().to_string(), "8E1");
    let s: EndSpec = "auto".parse().unwrap();
    assert_eq!(
        s,
        EndSpec {
            baud: None,
            format: None
        }
    );
    let s: EndSpec = "19200".parse().unwrap();
    assert_eq!(s.format, Some(Format::N81));
    assert!("0,8N1".parse::<EndSpec>().is_err());
    assert!("9600,9X9".parse::<EndSpec>().is_err());
}
