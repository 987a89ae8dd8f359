/* gpio-watch: scripts/gpio-check's watcher, on the device's side of a virtual line in the
 * emulated Pi: it relays bytes between the line's device end and a pty pair whose other
 * end the device opens, and samples a GPIO line's value (from /sys/kernel/debug/gpio)
 * between every two reads, so each byte and each change of the line is stamped on one
 * clock (CLOCK_MONOTONIC). Built by scripts/pi-check with the cross compiler, static.
 *
 * Usage: gpio-watch LINE_END DEVICE_LINK GPIO SECONDS OUT
 *   LINE_END     the device end of the line (`mbgate wire`'s B), opened here
 *   DEVICE_LINK  made here: a symbolic link to a fresh pty, for the device to open
 *   GPIO         the line as /sys/kernel/debug/gpio names it, e.g. gpio-517
 *   SECONDS      stop after this long (or at SIGTERM/SIGINT)
 *   OUT          the events, one a line, written at the end:
 *     G T_OLD V_OLD T_NEW V_NEW  the line changed: last sampled V_OLD by T_OLD (the
 *                                start of that sample), first V_NEW by T_NEW (its end)
 *     Q T_EMPTY T N V            N request bytes read at T from the line; the read
 *                                before, begun at T_EMPTY, found none; V: sampled after
 *     R T N V                    N reply bytes read at T from the device; V: sampled
 *                                after, before they are passed to the line
 *   Times in nanoseconds. V: 1 high, 0 low, -1 the line is not requested (not shown).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

struct ev {
    char kind;
    int n, v, v_old;
    long long t_old, t;
};

static volatile sig_atomic_t stop;
static void on_signal(int sig) { (void)sig; stop = 1; }

static long long now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static struct ev *evs;
static size_t nev, cap = 1 << 20;
static void push(struct ev e) {
    if (nev < cap) evs[nev++] = e;
}

static int dbg = -1;
static char needle[64];
static int last_v = -2;
static long long last_t0;

/* One sample: the line's value now, and a G event if it changed. */
static int sample(void) {
    static char buf[16384];
    long long t0 = now_ns();
    ssize_t n = pread(dbg, buf, sizeof buf - 1, 0);
    long long t1 = now_ns();
    int v = -1;
    if (n > 0) {
        buf[n] = 0;
        char *p = strstr(buf, needle);
        if (p) {
            char *eol = strchr(p, '\n');
            if (eol) *eol = 0;
            if (strstr(p, " hi")) v = 1;
            else if (strstr(p, " lo")) v = 0;
        }
    }
    if (v != last_v && last_v != -2)
        push((struct ev){.kind = 'G', .t_old = last_t0, .v_old = last_v, .t = t1, .v = v});
    last_v = v;
    last_t0 = t0;
    return v;
}

static void raw(int fd) {
    struct termios t;
    if (tcgetattr(fd, &t) == 0) {
        cfmakeraw(&t);
        tcsetattr(fd, TCSANOW, &t);
    }
}

static int write_all(int fd, const char *b, ssize_t n) {
    while (n > 0) {
        ssize_t w = write(fd, b, n);
        if (w < 0) {
            if (errno == EAGAIN || errno == EINTR) continue;
            return -1;
        }
        b += w;
        n -= w;
    }
    return 0;
}

int main(int argc, char **argv) {
    if (argc != 6) {
        fprintf(stderr, "usage: gpio-watch LINE_END DEVICE_LINK GPIO SECONDS OUT\n");
        return 2;
    }
    evs = calloc(cap, sizeof *evs);
    snprintf(needle, sizeof needle, " %s ", argv[3]);
    const char *gpio_file = getenv("GPIO_WATCH_FILE"); /* a stand-in, to try it without a chip */
    dbg = open(gpio_file ? gpio_file : "/sys/kernel/debug/gpio", O_RDONLY);
    if (dbg < 0) { perror("/sys/kernel/debug/gpio"); return 1; }
    int line = open(argv[1], O_RDWR | O_NOCTTY | O_NONBLOCK);
    if (line < 0) { perror(argv[1]); return 1; }
    raw(line);
    int master = posix_openpt(O_RDWR | O_NOCTTY | O_NONBLOCK);
    if (master < 0 || grantpt(master) || unlockpt(master)) { perror("pty"); return 1; }
    /* Held open here, so the master reads no hang-up while the device is away. */
    int slave = open(ptsname(master), O_RDWR | O_NOCTTY);
    if (slave < 0) { perror("pty slave"); return 1; }
    raw(slave);
    unlink(argv[2]);
    if (symlink(ptsname(master), argv[2])) { perror(argv[2]); return 1; }
    signal(SIGTERM, on_signal);
    signal(SIGINT, on_signal);
    long long end = now_ns() + atoll(argv[4]) * 1000000000LL;
    char buf[4096];
    long long t_empty = now_ns();
    sample();
    while (!stop && now_ns() < end) {
        sample();
        long long t_read = now_ns();
        ssize_t n = read(line, buf, sizeof buf);
        if (n > 0) {
            long long t = now_ns();
            int v = sample();
            push((struct ev){.kind = 'Q', .t_old = t_empty, .t = t, .n = (int)n, .v = v});
            if (write_all(master, buf, n)) { perror("to the device"); break; }
        } else {
            t_empty = t_read;
        }
        ssize_t m = read(master, buf, sizeof buf);
        if (m > 0) {
            long long t = now_ns();
            int v = sample();
            push((struct ev){.kind = 'R', .t = t, .n = (int)m, .v = v});
            if (write_all(line, buf, m)) { perror("to the line"); break; }
        }
    }
    unlink(argv[2]);
    FILE *out = fopen(argv[5], "w");
    if (!out) { perror(argv[5]); return 1; }
    for (size_t i = 0; i < nev; i++) {
        struct ev *e = &evs[i];
        if (e->kind == 'G')
            fprintf(out, "G %lld %d %lld %d\n", e->t_old, e->v_old, e->t, e->v);
        else if (e->kind == 'Q')
            fprintf(out, "Q %lld %lld %d %d\n", e->t_old, e->t, e->n, e->v);
        else
            fprintf(out, "R %lld %d %d\n", e->t, e->n, e->v);
    }
    fclose(out);
    return nev < cap ? 0 : 3;
}
