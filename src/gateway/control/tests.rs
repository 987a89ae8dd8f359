//! Tests of gateway::control.

use super::*;

#[test]
fn the_packaged_units_socket_follows_the_file_name() {
    assert_eq!(
        packaged_socket(Path::new("/etc/mbgate/mbgate.toml")),
        Path::new("/run/mbgate/control.sock")
    );
    assert_eq!(
        packaged_socket(Path::new("/etc/mbgate/ttyUSB0.toml")),
        Path::new("/run/mbgate@ttyUSB0/control.sock")
    );
}
