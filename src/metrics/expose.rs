//! The Prometheus text exposition of the gateway's numbers.
