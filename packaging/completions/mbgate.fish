# Print an optspec for argparse to handle cmd's options that are independent of any subcommand.
function __fish_mbgate_global_optspecs
    string join \n h/help V/version
end

function __fish_mbgate_needs_command
    # Figure out if the current invocation already has a command.
    set -l cmd (commandline -opc)
    set -e cmd[1]
    argparse -s (__fish_mbgate_global_optspecs) -- $cmd 2>/dev/null
    or return
    if set -q argv[1]
        # Also print the command, so this can be used to figure out what it is.
        echo $argv[1]
        return 1
    end
    return 0
end

function __fish_mbgate_using_subcommand
    set -l cmd (__fish_mbgate_needs_command)
    test -z "$cmd"
    and return 1
    contains -- $cmd[1] $argv
end

complete -c mbgate -n "__fish_mbgate_needs_command" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_needs_command" -s V -l version -d 'Print version'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "run" -d 'Run the gateway in the foreground (systemd does this)'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "check-config" -d 'Validate a configuration file and say what it sets up'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "read" -d 'Read coils, discrete inputs or registers (FC 01..04) and print them'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "write" -d 'Write coils or registers (FC 05, 06, 0F, 10; 17 with --read), print the reply'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "sim" -d 'A simulated device on a serial port or pty (a CIE-M10, or generic devices)'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "scan" -d 'Find what is on a bus: baud rate, format, framing and unit ids, by reads only'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "wire" -d 'A virtual serial line: two ptys joined like a null-modem cable, at the wire\'s pace'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "demo" -d 'No hardware: a pty pair, a simulated CIE-M10 and the gateway, in one process'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "status" -d 'Ask a running gateway how its lines are: a summary per line and unit'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "hash-password" -d 'Make a bcrypt hash of a password, for the metrics listener\'s users'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "capture" -d 'Capture a running gateway\'s frames to pcapng, for Wireshark (docs/capture.md)'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "generate" -d 'Man pages and shell completions, generated from this command line'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "reload" -d 'Have a running gateway read its configuration file again, and say what changed'
complete -c mbgate -n "__fish_mbgate_needs_command" -f -a "help" -d 'Print this message or the help of the given subcommand(s)'
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -s c -l config -d 'Configuration file (TOML, see config/mbgate.toml); without it, the defaults' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l serial -d 'Serial device of the Modbus device [serial.path] [default: /dev/ttyUSB0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l baud -d 'Serial speed in bit/s, 50..=4000000 [serial.baud_rate] [default: 19200]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l data-bits -d 'Data bits, 7 or 8 [serial.data_bits] [default: 8]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l parity -d 'Parity [serial.parity] [default: none]' -r -f -a "none\t''
even\t''
odd\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l stop-bits -d 'Stop bits, 1 or 2 [serial.stop_bits] [default: 1]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l flow-control -d 'Serial flow control [serial.flow_control] [default: hardware]' -r -f -a "hardware\t'RTS/CTS, as the device manual advises'
software\t'XON/XOFF'
none\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l framing -d 'Serial framing [serial.framing] [default: mbap]' -r -f -a "mbap\t'CIE-M10 serial Modbus/TCP: whole MBAP frames on the line (docs/protocol.md §3)'
rtu\t'Modbus RTU: unit, PDU, CRC-16; one transaction at a time'
ascii\t'Modbus ASCII: `:`, hex, LRC, CR LF; one transaction at a time'"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l port-kind -d 'What the port is: auto (learnt at each open), pty (no wire) or wire (a wire at baud_rate) [serial.port_kind] [default: auto]' -r -f -a "auto\t'Learnt at each open: a pseudo-terminal has no wire; a UART, a USB adapter or any other port is a wire at baud_rate'
pty\t'No wire whatever the port (a pty, a virtual port): a reply is taken however soon it comes'
wire\t'A wire at baud_rate whatever the port (a pty in front of a real line): echoes and replies begun before the request left are dropped'"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l low-latency -d 'Turn the driver\'s low latency on at each open (TIOCSSERIAL ASYNC_LOW_LATENCY, what setserial low_latency does; an FTDI adapter then hands bytes over every 1 ms) [serial.low_latency] [default: true]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l silence-floor-ms -d 'Least silence that ends a frame (RTU: a reply of unknown shape; MBAP: confirms a held reply); "auto": from the port (a pty 0, a UART its FIFO, a USB adapter its latency timer + 2), "auto" or 0 to 1000 [serial.silence_floor_ms] [default: auto]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l inter-frame-gap-us -d 'RTU/ASCII: silence before each request, in microseconds; 0 is the specification\'s (RTU: 3.5 characters, 1750 above 19 200 baud; ASCII: none after a whole reply), 0..=1000000 [serial.inter_frame_gap_us] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l rs485 -d 'Turn on the kernel\'s RS-485 mode (TIOCSRS485): RTS drives the transmitter [serial.rs485] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l rs485-delay-before-send-ms -d 'RS-485: RTS delay before sending, 0..=1000 ms [serial.rs485_delay_before_send_ms] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l rs485-delay-after-send-ms -d 'RS-485: RTS delay after sending, 0..=1000 ms [serial.rs485_delay_after_send_ms] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l echo -d 'The adapter echoes what is sent: read it back and discard it [serial.echo] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l direction -d 'RS-485: who switches the transmitter: none (the adapter, or the kernel with rs485 = true), rts or gpio (the gateway; RTU/ASCII lines) [serial.direction] [default: none]' -r -f -a "none\t'The gateway switches nothing: the adapter does it by itself, or the kernel does (rs485 = true)'
rts\t'The gateway asserts RTS while it sends (TIOCMBIS, TIOCMBIC): DE wired to RTS, a driver without RS-485 mode'
gpio\t'The gateway drives a GPIO line while it sends (the GPIO character device): DE wired to a GPIO pin'"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l direction-invert -d 'direction: the opposite level switches the transmitter on (RTS released, the GPIO line low while sending) [serial.direction_invert] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l direction-gpio-chip -d 'direction = "gpio": the GPIO chip by path (/dev/gpiochip0), name (gpiochip0) or label; "" (the default): gpiochip0, or for a line given by name, every chip [serial.direction_gpio_chip] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l direction-gpio-line -d 'direction = "gpio": the line by offset on its chip (17) or by name ("GPIO17") [serial.direction_gpio_line] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l direction-delay-before-us -d 'direction: microseconds between switching the transmitter on and the first byte, 0..=1000000 [serial.direction_delay_before_us] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l direction-delay-after-us -d 'direction: microseconds between the last stop bit leaving and switching the transmitter off, 0..=1000000 [serial.direction_delay_after_us] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l listen -d 'TCP address to listen on for Modbus/TCP masters [tcp.listen] [default: 0.0.0.0:502]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l max-connections -d 'Simultaneous master connections, 1..=4096 [tcp.max_connections] [default: 32]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l idle-timeout-ms -d 'Close a master connection idle this long, 0 (never) or a number of milliseconds [tcp.idle_timeout_ms] [default: 60000]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l response-timeout-ms -d 'Time to wait for the device\'s reply, 1..=600000 ms [relay.response_timeout_ms] [default: 1000]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l frame-gap-ms -d 'Silence after which a partial serial frame is discarded (MBAP: and a held reply taken while other replies are due), 1..=60000 ms [relay.frame_gap_ms] [default: 50]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l max-in-flight -d 'Requests outstanding on the serial line at once, 1..=255 [relay.max_in_flight] [default: 1]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l max-pending-per-connection -d 'Queued requests per master connection, 1..=1024 [relay.max_pending_per_connection] [default: 16]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l queue-depth -d 'Total queued requests, 1..=65536 [relay.queue_depth] [default: 64]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l retries -d 'Resends after a timeout (reads only unless --retry-writes), 0..=10 [relay.retries] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l retry-writes -d 'Also resend writes after a timeout (a resent write may act twice) [relay.retry_writes] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l notifications -d 'What to do with device frames that answer no request [relay.notifications] [default: drop]' -r -f -a "drop\t'Frames from the device that answer no request are dropped and counted'
broadcast\t'Well-formed unsolicited frames go to every connected master'"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l device-notifications -d 'MBAP: the device sends frames nobody asked for (the CIE-M10\'s input port change notification; off as shipped): every reply is then held for confirmation [relay.device_notifications] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l broadcast-delay-ms -d 'RTU/ASCII: quiet time after a broadcast (unit 0), 0..=60000 ms [relay.broadcast_delay_ms] [default: 100]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l broadcast-reply -d 'RTU/ASCII: what a master gets for a broadcast [relay.broadcast_reply] [default: none]' -r -f -a "none\t'The master gets nothing back (as on the bus)'
echo\t'The master gets the reply the device would have given'"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l unit-backoff -d 'RTU/ASCII: back off units that keep timing out [relay.unit_backoff] [default: true]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l unit-backoff-after -d 'Timeouts in a row that back a unit off, 1..=100 [relay.unit_backoff_after] [default: 3]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l unit-backoff-ms -d 'First back-off interval, 1..=3600000 ms [relay.unit_backoff_ms] [default: 1000]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l unit-backoff-max-ms -d 'Longest back-off interval, 1..=3600000 ms [relay.unit_backoff_max_ms] [default: 30000]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l probe-timeout-ms -d 'RTU/ASCII: response timeout of a request probing a backed-off unit, 1..=600000 ms [relay.probe_timeout_ms] [default: 250]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l timeout-guard-ms -d 'RTU/ASCII: quiet time after a timeout, late replies discarded, 0..=60000 ms [relay.timeout_guard_ms] [default: 100]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l coalesce -d 'A read identical to one waiting for the line (unit, function, address, count) joins it: one transaction, each master answered [relay.coalesce] [default: true]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l cache-ms -d 'Answer a read from the reply to the identical read if younger than this; a write to the unit clears it; 0 = off, 0..=3600000 ms [relay.cache_ms] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l request-pause-ms -d 'Quiet time after each reply before the next request, for slow devices, 0..=60000 ms [relay.request_pause_ms] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l log-level -d 'Log level (RUST_LOG overrides) [log.level] [default: info]' -r -f -a "trace\t''
debug\t''
info\t''
warn\t''
error\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l traffic -d 'Log every whole frame at debug level: direction, connection, unit, both transaction ids, function, address and count, hex [log.traffic] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l metrics-listen -d 'Address for Prometheus metrics (/metrics) and the status page; "" (the default): none [metrics.listen] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l metrics-web-config -d 'The metrics listener\'s web configuration file, in the format of Prometheus\' exporter-toolkit (TLS, client certificates, users with bcrypt hashes: docs/watching.md); "" (the default): plain HTTP, no users [metrics.web_config] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l capture-file -d 'Always-on capture to pcapng: the current file of a ring, the older ones FILE.1 to FILE.N-1; "" (the default): off [capture.file] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l capture-files -d 'Files in the capture ring, the current one included, 2..=1000 [capture.files] [default: 10]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l capture-file-size-kb -d 'Size of each file of the capture ring, in kB (1024 bytes), 16..=16777216 [capture.file_size_kb] [default: 10240]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -l control-socket -d 'Unix socket for mbgate capture, mode 0660 (root, the service\'s user and group); "" (the default): control.sock in systemd\'s RuntimeDirectory, none outside systemd [control.socket] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand run" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l serial -d 'Serial device of the Modbus device [serial.path] [default: /dev/ttyUSB0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l baud -d 'Serial speed in bit/s, 50..=4000000 [serial.baud_rate] [default: 19200]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l data-bits -d 'Data bits, 7 or 8 [serial.data_bits] [default: 8]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l parity -d 'Parity [serial.parity] [default: none]' -r -f -a "none\t''
even\t''
odd\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l stop-bits -d 'Stop bits, 1 or 2 [serial.stop_bits] [default: 1]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l flow-control -d 'Serial flow control [serial.flow_control] [default: hardware]' -r -f -a "hardware\t'RTS/CTS, as the device manual advises'
software\t'XON/XOFF'
none\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l framing -d 'Serial framing [serial.framing] [default: mbap]' -r -f -a "mbap\t'CIE-M10 serial Modbus/TCP: whole MBAP frames on the line (docs/protocol.md §3)'
rtu\t'Modbus RTU: unit, PDU, CRC-16; one transaction at a time'
ascii\t'Modbus ASCII: `:`, hex, LRC, CR LF; one transaction at a time'"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l port-kind -d 'What the port is: auto (learnt at each open), pty (no wire) or wire (a wire at baud_rate) [serial.port_kind] [default: auto]' -r -f -a "auto\t'Learnt at each open: a pseudo-terminal has no wire; a UART, a USB adapter or any other port is a wire at baud_rate'
pty\t'No wire whatever the port (a pty, a virtual port): a reply is taken however soon it comes'
wire\t'A wire at baud_rate whatever the port (a pty in front of a real line): echoes and replies begun before the request left are dropped'"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l low-latency -d 'Turn the driver\'s low latency on at each open (TIOCSSERIAL ASYNC_LOW_LATENCY, what setserial low_latency does; an FTDI adapter then hands bytes over every 1 ms) [serial.low_latency] [default: true]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l silence-floor-ms -d 'Least silence that ends a frame (RTU: a reply of unknown shape; MBAP: confirms a held reply); "auto": from the port (a pty 0, a UART its FIFO, a USB adapter its latency timer + 2), "auto" or 0 to 1000 [serial.silence_floor_ms] [default: auto]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l inter-frame-gap-us -d 'RTU/ASCII: silence before each request, in microseconds; 0 is the specification\'s (RTU: 3.5 characters, 1750 above 19 200 baud; ASCII: none after a whole reply), 0..=1000000 [serial.inter_frame_gap_us] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l rs485 -d 'Turn on the kernel\'s RS-485 mode (TIOCSRS485): RTS drives the transmitter [serial.rs485] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l rs485-delay-before-send-ms -d 'RS-485: RTS delay before sending, 0..=1000 ms [serial.rs485_delay_before_send_ms] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l rs485-delay-after-send-ms -d 'RS-485: RTS delay after sending, 0..=1000 ms [serial.rs485_delay_after_send_ms] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l echo -d 'The adapter echoes what is sent: read it back and discard it [serial.echo] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l direction -d 'RS-485: who switches the transmitter: none (the adapter, or the kernel with rs485 = true), rts or gpio (the gateway; RTU/ASCII lines) [serial.direction] [default: none]' -r -f -a "none\t'The gateway switches nothing: the adapter does it by itself, or the kernel does (rs485 = true)'
rts\t'The gateway asserts RTS while it sends (TIOCMBIS, TIOCMBIC): DE wired to RTS, a driver without RS-485 mode'
gpio\t'The gateway drives a GPIO line while it sends (the GPIO character device): DE wired to a GPIO pin'"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l direction-invert -d 'direction: the opposite level switches the transmitter on (RTS released, the GPIO line low while sending) [serial.direction_invert] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l direction-gpio-chip -d 'direction = "gpio": the GPIO chip by path (/dev/gpiochip0), name (gpiochip0) or label; "" (the default): gpiochip0, or for a line given by name, every chip [serial.direction_gpio_chip] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l direction-gpio-line -d 'direction = "gpio": the line by offset on its chip (17) or by name ("GPIO17") [serial.direction_gpio_line] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l direction-delay-before-us -d 'direction: microseconds between switching the transmitter on and the first byte, 0..=1000000 [serial.direction_delay_before_us] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l direction-delay-after-us -d 'direction: microseconds between the last stop bit leaving and switching the transmitter off, 0..=1000000 [serial.direction_delay_after_us] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l listen -d 'TCP address to listen on for Modbus/TCP masters [tcp.listen] [default: 0.0.0.0:502]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l max-connections -d 'Simultaneous master connections, 1..=4096 [tcp.max_connections] [default: 32]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l idle-timeout-ms -d 'Close a master connection idle this long, 0 (never) or a number of milliseconds [tcp.idle_timeout_ms] [default: 60000]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l response-timeout-ms -d 'Time to wait for the device\'s reply, 1..=600000 ms [relay.response_timeout_ms] [default: 1000]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l frame-gap-ms -d 'Silence after which a partial serial frame is discarded (MBAP: and a held reply taken while other replies are due), 1..=60000 ms [relay.frame_gap_ms] [default: 50]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l max-in-flight -d 'Requests outstanding on the serial line at once, 1..=255 [relay.max_in_flight] [default: 1]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l max-pending-per-connection -d 'Queued requests per master connection, 1..=1024 [relay.max_pending_per_connection] [default: 16]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l queue-depth -d 'Total queued requests, 1..=65536 [relay.queue_depth] [default: 64]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l retries -d 'Resends after a timeout (reads only unless --retry-writes), 0..=10 [relay.retries] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l retry-writes -d 'Also resend writes after a timeout (a resent write may act twice) [relay.retry_writes] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l notifications -d 'What to do with device frames that answer no request [relay.notifications] [default: drop]' -r -f -a "drop\t'Frames from the device that answer no request are dropped and counted'
broadcast\t'Well-formed unsolicited frames go to every connected master'"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l device-notifications -d 'MBAP: the device sends frames nobody asked for (the CIE-M10\'s input port change notification; off as shipped): every reply is then held for confirmation [relay.device_notifications] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l broadcast-delay-ms -d 'RTU/ASCII: quiet time after a broadcast (unit 0), 0..=60000 ms [relay.broadcast_delay_ms] [default: 100]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l broadcast-reply -d 'RTU/ASCII: what a master gets for a broadcast [relay.broadcast_reply] [default: none]' -r -f -a "none\t'The master gets nothing back (as on the bus)'
echo\t'The master gets the reply the device would have given'"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l unit-backoff -d 'RTU/ASCII: back off units that keep timing out [relay.unit_backoff] [default: true]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l unit-backoff-after -d 'Timeouts in a row that back a unit off, 1..=100 [relay.unit_backoff_after] [default: 3]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l unit-backoff-ms -d 'First back-off interval, 1..=3600000 ms [relay.unit_backoff_ms] [default: 1000]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l unit-backoff-max-ms -d 'Longest back-off interval, 1..=3600000 ms [relay.unit_backoff_max_ms] [default: 30000]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l probe-timeout-ms -d 'RTU/ASCII: response timeout of a request probing a backed-off unit, 1..=600000 ms [relay.probe_timeout_ms] [default: 250]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l timeout-guard-ms -d 'RTU/ASCII: quiet time after a timeout, late replies discarded, 0..=60000 ms [relay.timeout_guard_ms] [default: 100]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l coalesce -d 'A read identical to one waiting for the line (unit, function, address, count) joins it: one transaction, each master answered [relay.coalesce] [default: true]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l cache-ms -d 'Answer a read from the reply to the identical read if younger than this; a write to the unit clears it; 0 = off, 0..=3600000 ms [relay.cache_ms] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l request-pause-ms -d 'Quiet time after each reply before the next request, for slow devices, 0..=60000 ms [relay.request_pause_ms] [default: 0]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l log-level -d 'Log level (RUST_LOG overrides) [log.level] [default: info]' -r -f -a "trace\t''
debug\t''
info\t''
warn\t''
error\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l traffic -d 'Log every whole frame at debug level: direction, connection, unit, both transaction ids, function, address and count, hex [log.traffic] [default: false]' -r -f -a "true\t''
false\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l metrics-listen -d 'Address for Prometheus metrics (/metrics) and the status page; "" (the default): none [metrics.listen] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l metrics-web-config -d 'The metrics listener\'s web configuration file, in the format of Prometheus\' exporter-toolkit (TLS, client certificates, users with bcrypt hashes: docs/watching.md); "" (the default): plain HTTP, no users [metrics.web_config] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l capture-file -d 'Always-on capture to pcapng: the current file of a ring, the older ones FILE.1 to FILE.N-1; "" (the default): off [capture.file] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l capture-files -d 'Files in the capture ring, the current one included, 2..=1000 [capture.files] [default: 10]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l capture-file-size-kb -d 'Size of each file of the capture ring, in kB (1024 bytes), 16..=16777216 [capture.file_size_kb] [default: 10240]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l control-socket -d 'Unix socket for mbgate capture, mode 0660 (root, the service\'s user and group); "" (the default): control.sock in systemd\'s RuntimeDirectory, none outside systemd [control.socket] [default: ]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l print -d 'Print the whole effective configuration, every key with its value, as TOML'
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -l lines -d 'Print the whole effective configuration as [[line]] and [[listen]] tables (docs/design.md §4.1)'
complete -c mbgate -n "__fish_mbgate_using_subcommand check-config" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l tcp -d 'Gateway or Modbus/TCP device, HOST[:PORT] (port 502 if left out) [default: 127.0.0.1:502]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l serial -d 'Ask a device directly on this serial port, in MBAP framing (the CIE-M10 serial Modbus/TCP mode: whole MBAP frames on the line, no CRC) unless --framing says otherwise' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l framing -d 'How frames are carried: mbap, or rtu or ascii for a Modbus serial-line device on --serial, or for RTU over TCP on --tcp (a gateway\'s rtu listener, a serial device server in raw TCP mode)' -r -f -a "mbap\t'CIE-M10 serial Modbus/TCP: whole MBAP frames on the line (docs/protocol.md §3)'
rtu\t'Modbus RTU: unit, PDU, CRC-16; one transaction at a time'
ascii\t'Modbus ASCII: `:`, hex, LRC, CR LF; one transaction at a time'"
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l baud -d 'Serial speed in bit/s, 50..=4000000 [serial.baud_rate] [default: 19200]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l data-bits -d 'Data bits, 7 or 8 [serial.data_bits] [default: 8]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l parity -d 'Parity [serial.parity] [default: none]' -r -f -a "none\t''
even\t''
odd\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l stop-bits -d 'Stop bits, 1 or 2 [serial.stop_bits] [default: 1]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l flow-control -d 'Serial flow control [serial.flow_control] [default: hardware]' -r -f -a "hardware\t'RTS/CTS, as the device manual advises'
software\t'XON/XOFF'
none\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -s u -l unit -d 'Unit id (slave address), 0..=255' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l timeout-ms -d 'Give up on a reply after this long (a gateway answers 0x0B after its own response timeout, 1000 ms by default, so wait longer than that)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l poll -d 'Repeat every MS milliseconds until Ctrl-C (or --count), printing each result with a timestamp' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -l count -d 'With --poll: stop after N requests' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -s v -l verbose -d 'Print both frames (request and reply) as hex'
complete -c mbgate -n "__fish_mbgate_using_subcommand read" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l tcp -d 'Gateway or Modbus/TCP device, HOST[:PORT] (port 502 if left out) [default: 127.0.0.1:502]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l serial -d 'Ask a device directly on this serial port, in MBAP framing (the CIE-M10 serial Modbus/TCP mode: whole MBAP frames on the line, no CRC) unless --framing says otherwise' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l framing -d 'How frames are carried: mbap, or rtu or ascii for a Modbus serial-line device on --serial, or for RTU over TCP on --tcp (a gateway\'s rtu listener, a serial device server in raw TCP mode)' -r -f -a "mbap\t'CIE-M10 serial Modbus/TCP: whole MBAP frames on the line (docs/protocol.md §3)'
rtu\t'Modbus RTU: unit, PDU, CRC-16; one transaction at a time'
ascii\t'Modbus ASCII: `:`, hex, LRC, CR LF; one transaction at a time'"
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l baud -d 'Serial speed in bit/s, 50..=4000000 [serial.baud_rate] [default: 19200]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l data-bits -d 'Data bits, 7 or 8 [serial.data_bits] [default: 8]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l parity -d 'Parity [serial.parity] [default: none]' -r -f -a "none\t''
even\t''
odd\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l stop-bits -d 'Stop bits, 1 or 2 [serial.stop_bits] [default: 1]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l flow-control -d 'Serial flow control [serial.flow_control] [default: hardware]' -r -f -a "hardware\t'RTS/CTS, as the device manual advises'
software\t'XON/XOFF'
none\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -s u -l unit -d 'Unit id (slave address), 0..=255' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l timeout-ms -d 'Give up on a reply after this long (a gateway answers 0x0B after its own response timeout, 1000 ms by default, so wait longer than that)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l poll -d 'Repeat every MS milliseconds until Ctrl-C (or --count), printing each result with a timestamp' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l count -d 'With --poll: stop after N requests' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l read -d 'FC 17 (registers only): in the same transaction, after the write, read COUNT registers at ADDR and print them' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -s v -l verbose -d 'Print both frames (request and reply) as hex'
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -l multiple -d 'Use FC 0F / 10 even for a single value'
complete -c mbgate -n "__fish_mbgate_using_subcommand write" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l serial -d 'The serial port or pty (e.g. one end of a socat pair)' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l pty -d 'Make a pty instead, linked at PATH (as socat\'s `link=`), and serve on it: point the gateway\'s serial port at PATH. No relay process sits between the two ends, so a replayed device\'s reply time is not lengthened by one (docs/simulator.md "Replaying a device")' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l listen -d 'A device on the network instead: listen here (e.g. 127.0.0.1:1502) and serve one connection at a time, as a Modbus/TCP slave (--framing mbap) or a serial device server in raw TCP mode (--framing rtu or ascii)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l connections -d 'With --listen: how many connections are served at once. 1 (the default): a second is closed at once, as a device server or a single-connection PLC does; more: a Modbus/TCP slave that several masters reach at once (--framing mbap)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l profile -d 'The simulated device' -r -f -a "cie-m10\t'The Sollae CIE-M10/H10 of docs/protocol.md §3: 8 inputs, 8 outputs, FC 03 and 16'
generic\t'Devices by unit id with all four tables, FC 01-06, 0F, 10, 17'"
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l unit -d 'cie-m10: the unit id it answers' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l input-address -d 'cie-m10: register of the 8 input ports' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l output-address -d 'cie-m10: register of the 8 output ports' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l toggle-ms -d 'Change the inputs on a schedule: they count up by one every MS (cie-m10); the generic profile counts the changes' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l units -d 'generic: unit ids of the devices, comma separated' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l fill -d 'generic: holding registers start at zero, or each at its own address (so a reader can check every value it gets)' -r -f -a "zero\t''
address\t''
header\t'Pieces of MBAP headers (`generic::HEADER_FILL`, repeating every 12 registers): replies that spell frames, to put a gateway\'s decoder to the test'"
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l coils -d 'generic: coils and discrete inputs per device (at least 10)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l registers -d 'generic: holding and input registers per device (at least 10)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l delay-ms -d 'Wait this long before answering each request' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l drop -d 'Lose each byte with this probability (0..1)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l noise -d 'Insert a burst of 1 to 8 random bytes before each byte with this probability (0..1)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l corrupt -d 'Replace each byte by another with this probability (0..1): a bit error, which MBAP has no checksum to catch' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l faults -d 'Which direction --drop, --noise and --corrupt hit' -r -f -a "both\t''
to-device\t'Bytes the gateway sends to the device'
from-device\t'Bytes the device sends to the gateway'"
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l seed -d 'Seed of the line faults and of random inputs: the same seed loses the same bytes. Without it, one is chosen and logged' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l chunks -d 'Hand each frame to the line whole, one byte at a time, or in random bursts of 1 to 8 bytes, with --chunk-gap-ms between the pieces' -r -f -a "whole\t''
bytes\t''
random\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l chunk-gap-ms -d 'The gap between pieces: exactly this one byte at a time, between half of it and all of it in random bursts' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l frame-gap-ms -d 'A partial request is discarded after this much silence' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l log-level -d 'Log level (RUST_LOG overrides). Each packet is logged at info' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l replay -d 'Replay the devices a capture of `mbgate capture` (or its `[capture] file` ring) recorded on the gateway\'s lines, instead of a profile. Repeat for several files (a ring, several days): where they disagree, the latest wins. The profiles\' flags do not apply' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l unknown-exception -d 'The exception for an address the capture never saw read (02, illegal data address, by default)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l role -d 'slave answers requests; master sends, every --poll-ms, FC 03 for the slave\'s input port register and FC 16 with its own inputs to the slave\'s output port register (the --input-address and --output-address), and sets its outputs from what it read' -r -f -a "slave\t'It answers requests (the default)'
master\t'It sends the CIE-M10 master\'s queries every --poll-ms (cie-m10 profile)'"
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l poll-ms -d 'master: the communication period, in ms' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l timeout-ms -d 'master: how long it waits for each reply, in ms [default: the period, at most 1000]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l baud -d 'Serial speed in bit/s, 50..=4000000 [serial.baud_rate] [default: 19200]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l data-bits -d 'Data bits, 7 or 8 [serial.data_bits] [default: 8]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l parity -d 'Parity [serial.parity] [default: none]' -r -f -a "none\t''
even\t''
odd\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l stop-bits -d 'Stop bits, 1 or 2 [serial.stop_bits] [default: 1]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l flow-control -d 'Serial flow control [serial.flow_control] [default: hardware]' -r -f -a "hardware\t'RTS/CTS, as the device manual advises'
software\t'XON/XOFF'
none\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l framing -d 'How frames are carried: mbap (the CIE-M10\'s serial Modbus/TCP), or rtu or ascii (generic profile and --replay only) [default: mbap; with --replay, as recorded]' -r -f -a "mbap\t'CIE-M10 serial Modbus/TCP: whole MBAP frames on the line (docs/protocol.md §3)'
rtu\t'Modbus RTU: unit, PDU, CRC-16; one transaction at a time'
ascii\t'Modbus ASCII: `:`, hex, LRC, CR LF; one transaction at a time'"
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l loopback -d 'cie-m10: wire each output to its input, so inputs follow the outputs'
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l notify -d 'Input port change notification, an unsolicited FC 03 response (transaction id 0) whenever an input changes (cie-m10), or on each scheduled change (generic: from the first unit, carrying the count of changes)'
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l pipeline -d 'Answer requests that arrive back to back (pipelined) in turn; without it, a request that arrives while the device is busy is ignored, as on the real device'
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l confirm-requests -d 'Hold each request until the bytes after it start another, or the line goes quiet, so a request that lost a byte is never executed with the next one\'s first byte. Costs up to --frame-gap-ms whenever the gateway pauses its pipeline'
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l headless -d 'No console even when stdin is a terminal'
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l timeline -d 'Play the values back over time as they were recorded (from the capture\'s start, at its pace; the last value after its end), rather than the last seen'
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l read-only -d 'Refuse every write, with the exception the device gave to a write if the capture has one, else 01 (illegal function). Without it, writes change the replayed values'
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -l summary -d 'Say what the files hold, unit by unit, and exit'
complete -c mbgate -n "__fish_mbgate_using_subcommand sim" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l tcp -d 'Scan a Modbus/TCP device or gateway at HOST:PORT instead: unit ids only' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l baud -d 'The baud rates to try, in order [default: 19200,9600,115200,38400,57600,4800,2400,1200]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l format -d 'The formats to try, in order [default: 8E1,8N1,8N2,8O1]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l framing -d 'The framings to try, in order [default: rtu,ascii]' -r -f -a "rtu\t'Modbus RTU: binary, CRC-16'
ascii\t'Modbus ASCII: hex between `:` and CR LF, LRC'"
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l units -d 'The unit ids to try: ids and ranges, `1-247`, `1,2,10-20`' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l timeout-ms -d 'How long a device may take to answer, beyond the request\'s and the reply\'s own time on the wire (a later reply still counts, in the next units\' time)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l give-up -d 'Leave a setting after this many units got no frame with a good CRC or LRC (a setting that got one is scanned to the last unit; so are 19200 and 9600 baud, 8E1 and 8N1, RTU and ASCII, the settings most buses use)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l listen-secs -d 'With --listen: how long to listen at each setting' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l all -d 'Go on to the other settings after one is found (a bus has one setting, so by default the scan ends with the first that answers)'
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l listen -d 'Send nothing: listen to a live bus at each setting in turn and report the setting, units, function codes, request rate and reply times heard'
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -l json -d 'Print the result as JSON instead of a table'
complete -c mbgate -n "__fish_mbgate_using_subcommand scan" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand wire" -l format -d 'Both ends\' format, FORMAT or BAUD,FORMAT: 8N1, 8E1, 8O1, 8N2, 7E1...; or `auto`: the parity and stop bits the program set, where a pty still shows them (PARODD: odd; INPCK without it: even, as serialport and so mbgate set it; pyserial\'s even parity reads as none). A baud rate given here is used whatever the program sets; otherwise each end\'s speed is the one its program set' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand wire" -l a -d 'End A\'s format, as --format (which it overrides)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand wire" -l b -d 'End B\'s format, as --format (which it overrides)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand wire" -l loss -d 'The share of characters lost on the wire, 0 to 1 (the receiver hears an idle line for them)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand wire" -l noise -d 'The share of characters with one bit flipped on the wire, 0 to 1 (any bit: a data bit, the parity bit, the start or a stop bit)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand wire" -l seed -d 'The seed of loss and noise: the same seed, the same faults for the same bytes' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand wire" -l echo -d 'RS-232 echo: each end hears what it sends too (as it left, before loss and noise), as a 2-wire RS-485 transceiver or a loopback adapter does'
complete -c mbgate -n "__fish_mbgate_using_subcommand wire" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l listen -d 'Where Modbus/TCP masters connect [default: 127.0.0.1:5020, or a free port when another program holds 5020]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l baud -d 'Pace the simulated device\'s output at this many bits a second (10 bits a byte), as a UART would' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l lines -d 'Two lines behind the one address: a second pty pair with the same simulated device, its units reached as unit + 100 (routing by unit, with remapping)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l profile -d 'The simulated device' -r -f -a "cie-m10\t'The Sollae CIE-M10/H10 of docs/protocol.md §3: 8 inputs, 8 outputs, FC 03 and 16'
generic\t'Devices by unit id with all four tables, FC 01-06, 0F, 10, 17'"
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l unit -d 'cie-m10: the unit id it answers' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l input-address -d 'cie-m10: register of the 8 input ports' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l output-address -d 'cie-m10: register of the 8 output ports' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l toggle-ms -d 'Change the inputs on a schedule: they count up by one every MS (cie-m10); the generic profile counts the changes' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l units -d 'generic: unit ids of the devices, comma separated' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l fill -d 'generic: holding registers start at zero, or each at its own address (so a reader can check every value it gets)' -r -f -a "zero\t''
address\t''
header\t'Pieces of MBAP headers (`generic::HEADER_FILL`, repeating every 12 registers): replies that spell frames, to put a gateway\'s decoder to the test'"
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l coils -d 'generic: coils and discrete inputs per device (at least 10)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l registers -d 'generic: holding and input registers per device (at least 10)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l delay-ms -d 'Wait this long before answering each request' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l drop -d 'Lose each byte with this probability (0..1)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l noise -d 'Insert a burst of 1 to 8 random bytes before each byte with this probability (0..1)' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l corrupt -d 'Replace each byte by another with this probability (0..1): a bit error, which MBAP has no checksum to catch' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l faults -d 'Which direction --drop, --noise and --corrupt hit' -r -f -a "both\t''
to-device\t'Bytes the gateway sends to the device'
from-device\t'Bytes the device sends to the gateway'"
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l seed -d 'Seed of the line faults and of random inputs: the same seed loses the same bytes. Without it, one is chosen and logged' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l chunks -d 'Hand each frame to the line whole, one byte at a time, or in random bursts of 1 to 8 bytes, with --chunk-gap-ms between the pieces' -r -f -a "whole\t''
bytes\t''
random\t''"
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l chunk-gap-ms -d 'The gap between pieces: exactly this one byte at a time, between half of it and all of it in random bursts' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l frame-gap-ms -d 'A partial request is discarded after this much silence' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l log-level -d 'Log level (RUST_LOG overrides). Each packet is logged at info' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l poll-ms -d '--master: the master\'s communication period, in ms' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l traffic -d 'Log every frame the gateway relays, both directions, as hex'
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l loopback -d 'cie-m10: wire each output to its input, so inputs follow the outputs'
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l notify -d 'Input port change notification, an unsolicited FC 03 response (transaction id 0) whenever an input changes (cie-m10), or on each scheduled change (generic: from the first unit, carrying the count of changes)'
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l pipeline -d 'Answer requests that arrive back to back (pipelined) in turn; without it, a request that arrives while the device is busy is ignored, as on the real device'
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l confirm-requests -d 'Hold each request until the bytes after it start another, or the line goes quiet, so a request that lost a byte is never executed with the next one\'s first byte. Costs up to --frame-gap-ms whenever the gateway pauses its pipeline'
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l headless -d 'No console even when stdin is a terminal'
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -l master -d 'The device as master: a simulated CIE-M10 master, mbgate\'s master line and a simulated CIE-M10 slave on Modbus/TCP (at --listen)'
complete -c mbgate -n "__fish_mbgate_using_subcommand demo" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand status" -l metrics -d 'The gateway\'s metrics listener: ADDR, http://ADDR or https://ADDR (its metrics.listen) [default: over the control socket when there is one, else 127.0.0.1:9502]' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand status" -l ca -d 'https: the CA the gateway\'s certificate chains to [default: /etc/ssl/certs/ca-certificates.crt]' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand status" -l cert -d 'https: a client certificate, for a listener that asks for one (with --key)' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand status" -l key -d 'https: the key of --cert' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand status" -l user -d 'A user of the listener\'s web configuration; the password from the environment variable MBGATE_PASSWORD or --password-file' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand status" -l password-file -d 'A file whose first line is the password of --user' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand status" -l socket -d 'Ask over the gateway\'s control socket (root, or the service\'s user or group; no password) [default: from the configuration file]' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand status" -s c -l config -d 'The gateway\'s configuration file, to find its control socket [default: /etc/mbgate/mbgate.toml]' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand status" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand hash-password" -l cost -d 'bcrypt\'s cost: each step doubles the time of a check (10: about 50 ms on a PC, some hundreds on a Raspberry Pi); 4 to 16' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand hash-password" -l user -d 'Print `NAME: HASH`, a line of basic_auth_users' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand hash-password" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand capture" -s o -l output -d 'Where to write: a file, or - for standard output (`-o - | wireshark -k -i -`)' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand capture" -l socket -d 'The gateway\'s control socket [default: from the configuration file]' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand capture" -s c -l config -d 'The gateway\'s configuration file, to find its control socket (control.socket; empty: the packaged unit\'s runtime directory for this file) [default: /etc/mbgate/mbgate.toml]' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand capture" -l line -d 'Only this line: its index (0 is the first [[line]]), its name (/dev/ttyUSB0, host:port), or tcp for the masters\' side; repeat for several' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand capture" -l unit -d 'Only this unit id (dropped bytes, which have none, are kept); repeat for several' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand capture" -l master -d 'Only this master\'s packets, by its address (10.0.0.5) or address and port (10.0.0.5:40000), and the line\'s frames for its requests; repeat for several' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand capture" -l function -d 'Only this function code (decimal or 0x10; its exceptions too); repeat for several' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand capture" -l count -d 'Stop after this many packets' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand capture" -l seconds -d 'Stop after this many seconds' -r
complete -c mbgate -n "__fish_mbgate_using_subcommand capture" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand generate; and not __fish_seen_subcommand_from man completions help" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand generate; and not __fish_seen_subcommand_from man completions help" -f -a "man" -d 'Write the man pages into DIR: mbgate(1), mbgate-SUBCOMMAND(1) for each subcommand, and mbgate.toml(5), the configuration file'
complete -c mbgate -n "__fish_mbgate_using_subcommand generate; and not __fish_seen_subcommand_from man completions help" -f -a "completions" -d 'Print the completion script for SHELL'
complete -c mbgate -n "__fish_mbgate_using_subcommand generate; and not __fish_seen_subcommand_from man completions help" -f -a "help" -d 'Print this message or the help of the given subcommand(s)'
complete -c mbgate -n "__fish_mbgate_using_subcommand generate; and __fish_seen_subcommand_from man" -s h -l help -d 'Print help'
complete -c mbgate -n "__fish_mbgate_using_subcommand generate; and __fish_seen_subcommand_from completions" -s h -l help -d 'Print help'
complete -c mbgate -n "__fish_mbgate_using_subcommand generate; and __fish_seen_subcommand_from help" -f -a "man" -d 'Write the man pages into DIR: mbgate(1), mbgate-SUBCOMMAND(1) for each subcommand, and mbgate.toml(5), the configuration file'
complete -c mbgate -n "__fish_mbgate_using_subcommand generate; and __fish_seen_subcommand_from help" -f -a "completions" -d 'Print the completion script for SHELL'
complete -c mbgate -n "__fish_mbgate_using_subcommand generate; and __fish_seen_subcommand_from help" -f -a "help" -d 'Print this message or the help of the given subcommand(s)'
complete -c mbgate -n "__fish_mbgate_using_subcommand reload" -l socket -d 'The gateway\'s control socket [default: from the configuration file]' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand reload" -s c -l config -d 'The gateway\'s configuration file, to find its control socket (control.socket; empty: the packaged unit\'s runtime directory for this file) [default: /etc/mbgate/mbgate.toml]' -r -F
complete -c mbgate -n "__fish_mbgate_using_subcommand reload" -s h -l help -d 'Print help (see more with \'--help\')'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "run" -d 'Run the gateway in the foreground (systemd does this)'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "check-config" -d 'Validate a configuration file and say what it sets up'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "read" -d 'Read coils, discrete inputs or registers (FC 01..04) and print them'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "write" -d 'Write coils or registers (FC 05, 06, 0F, 10; 17 with --read), print the reply'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "sim" -d 'A simulated device on a serial port or pty (a CIE-M10, or generic devices)'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "scan" -d 'Find what is on a bus: baud rate, format, framing and unit ids, by reads only'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "wire" -d 'A virtual serial line: two ptys joined like a null-modem cable, at the wire\'s pace'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "demo" -d 'No hardware: a pty pair, a simulated CIE-M10 and the gateway, in one process'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "status" -d 'Ask a running gateway how its lines are: a summary per line and unit'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "hash-password" -d 'Make a bcrypt hash of a password, for the metrics listener\'s users'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "capture" -d 'Capture a running gateway\'s frames to pcapng, for Wireshark (docs/capture.md)'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "generate" -d 'Man pages and shell completions, generated from this command line'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "reload" -d 'Have a running gateway read its configuration file again, and say what changed'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and not __fish_seen_subcommand_from run check-config read write sim scan wire demo status hash-password capture generate reload help" -f -a "help" -d 'Print this message or the help of the given subcommand(s)'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and __fish_seen_subcommand_from generate" -f -a "man" -d 'Write the man pages into DIR: mbgate(1), mbgate-SUBCOMMAND(1) for each subcommand, and mbgate.toml(5), the configuration file'
complete -c mbgate -n "__fish_mbgate_using_subcommand help; and __fish_seen_subcommand_from generate" -f -a "completions" -d 'Print the completion script for SHELL'
