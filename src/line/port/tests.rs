//! Tests of line::port.

use super::*;

#[test]
fn backoff_doubles_up_to_max_and_resets() {
    let mut b = Backoff::new(Duration::from_millis(100), Duration::from_millis(500));
    let got: Vec<u64> = (0..5).map(|_| b.next_delay().as_millis() as u64).collect();
    assert_eq!(got, [100, 200, 400, 500, 500]);
    b.reset();
    assert_eq!(b.next_delay(), Duration::from_millis(100));
}

/// An open port is let go control first: its transmitter is switched off while
/// the descriptor the halves close is still open (it once was switched after,
/// on a closed descriptor: EBADF, the switch never made).
#[test]
fn an_open_port_drops_its_control_before_its_halves() {
    use std::sync::{Arc, Mutex};
    type Order = Arc<Mutex<Vec<&'static str>>>;
    struct Half(Order, &'static str);
    impl Drop for Half {
        fn drop(&mut self) {
            self.0.lock().unwrap().push(self.1);
        }
    }
    impl AsyncRead for Half {
        fn poll_read(
            self: Pin<&mut Self>,
            _: &mut std::task::Context<'_>,
            _: &mut tokio::io::ReadBuf<'_>,
        ) -> std::task::Poll<io::Result<()>> {
            std::task::Poll::Pending
        }
    }
    impl AsyncWrite for Half {
        fn poll_write(
            self: Pin<&mut Self>,
            _: &mut std::task::Context<'_>,
            _: &[u8],
        ) -> std::task::Poll<io::Result<usize>> {
            std::task::Poll::Pending
        }
        fn poll_flush(
            self: Pin<&mut Self>,
            _: &mut std::task::Context<'_>,
        ) -> std::task::Poll<io::Result<()>> {
            std::task::Poll::Ready(Ok(()))
        }
        fn poll_shutdown(
            self: Pin<&mut Self>,
            _: &mut std::task::Context<'_>,
        ) -> std::task::Poll<io::Result<()>> {
            std::task::Poll::Ready(Ok(()))
        }
    }
    impl Control for Half {}
    let order: Order = Arc::default();
    let port = OpenPort {
        reader: Box::new(Half(order.clone(), "reader")),
        writer: Box::new(Half(order.clone(), "writer")),
        control: Box::new(Half(order.clone(), "control")),
        info: kind::PortInfo::unknown(),
    };
    drop(port);
    assert_eq!(*order.lock().unwrap(), ["control", "reader", "writer"]);
}
