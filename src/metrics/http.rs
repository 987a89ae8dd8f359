//! The metrics listener: a minimal HTTP/1.1 server for GET only.
