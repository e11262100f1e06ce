/* goto_point.c: a robot's C side of mocapd's serial line: read the pose packets off a UART
 * (or the simulator's pseudo-terminal) with mocapd_packet.h, and print every pose or drive
 * to points, as a robot's firmware would.
 *
 *   cc -std=c99 -Wall -I daemon/publish -o goto_point examples/goto_point.c -lm
 *   ./goto_point /dev/ttyUSB0 [BAUD] [PACKETS]                      print poses
 *   ./goto_point /dev/ttyUSB0 BAUD 0 BODY PORT X,Y [X,Y ...]         drive to the points
 *
 * Printing, each line: frame t_ns body_id valid x y z qx qy qz qw yaw_rad (floats as %.9g,
 * which gives back the packet's float32 exactly). Stops after PACKETS packets (0: never).
 *
 * Driving: body BODY is the robot; commands "V OMEGA" go to 127.0.0.1:PORT (the simulated
 * robot of [sim.robot]; on a real robot, the motor driver). The controller is
 * examples/goto_point.py's: bearing and distance, backwards when the target is behind,
 * stop near it, settle, and count it reached when settled within 1 cm. Prints
 *   target K (X, Y): reached, error E mm (pose t_ns T)
 * per target, and exits 0 once every one is reached.
 *
 * Frames that fail COBS or the CRC (the partial one a reader starts in the middle of, a
 * glitch) are counted and skipped; the count goes to stderr at the end.
 */
#define _DEFAULT_SOURCE /* cfmakeraw */
#include <arpa/inet.h>
#include <fcntl.h>
#include <math.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <stdio.h>
#include <stdlib.h>
#include <termios.h>
#include <unistd.h>

#include "mocapd_packet.h"

#define MAX_FRAME 4096
#define MAX_TARGETS 64
#define TOLERANCE_M 0.01
#define SETTLE_PACKETS 40 /* 0.4 s at 100 Hz stopped before a target's error is taken */
#define MAX_SPEED 0.4
#define MAX_TURN 2.5

static speed_t baud_constant(long baud) {
    switch (baud) {
    case 9600: return B9600;
    case 19200: return B19200;
    case 38400: return B38400;
    case 57600: return B57600;
    case 115200: return B115200;
    case 230400: return B230400;
    case 460800: return B460800;
    case 921600: return B921600;
    default: return B0;
    }
}

static int open_line(const char *path, long baud) {
    int fd = open(path, O_RDONLY | O_NOCTTY);
    if (fd < 0) return -1;
    if (isatty(fd)) {
        struct termios t;
        speed_t speed = baud_constant(baud);
        if (speed == B0 || tcgetattr(fd, &t) < 0) { close(fd); return -1; }
        cfmakeraw(&t);
        cfsetispeed(&t, speed);
        cfsetospeed(&t, speed);
        t.c_cc[VMIN] = 1;
        t.c_cc[VTIME] = 0;
        if (tcsetattr(fd, TCSANOW, &t) < 0) { close(fd); return -1; }
    }
    return fd;
}

/* Heading about z of a body-to-world quaternion (x, y, z, w). */
static double yaw_of(const float q[4]) {
    return atan2(2.0 * ((double)q[3] * q[2] + (double)q[0] * q[1]),
                 1.0 - 2.0 * ((double)q[1] * q[1] + (double)q[2] * q[2]));
}

static double wrap(double a) {
    a = fmod(a + M_PI, 2.0 * M_PI);
    return (a < 0 ? a + 2.0 * M_PI : a) - M_PI;
}

/* goto_point.py's steer(): (v, omega) towards (tx, ty) from (x, y, yaw). */
static void steer(double x, double y, double yaw, double tx, double ty, double *v, double *w) {
    double rho = hypot(tx - x, ty - y), alpha = wrap(atan2(ty - y, tx - x) - yaw), sign = 1.0;
    if (fabs(alpha) > M_PI / 2) { alpha = wrap(alpha + M_PI); sign = -1.0; }
    double c = cos(alpha) > 0 ? cos(alpha) : 0.0;
    *v = sign * fmin(MAX_SPEED, 1.5 * rho) * c * c;
    *w = fmax(-MAX_TURN, fmin(MAX_TURN, 3.0 * alpha));
}

typedef struct {
    int sock;
    struct sockaddr_in to;
    int body, n, k, settling;
    double tx[MAX_TARGETS], ty[MAX_TARGETS];
} driver_t;

static void send_command(driver_t *d, double v, double w) {
    char msg[64];
    int len = snprintf(msg, sizeof msg, "%.5f %.5f", v, w);
    sendto(d->sock, msg, (size_t)len, 0, (struct sockaddr *)&d->to, sizeof d->to);
}

/* One packet's step of the controller; 1 when every target is reached. */
static int drive_packet(driver_t *d, const uint8_t *buf, const mocapd_header_t *h) {
    for (int i = 0; i < h->count; i++) {
        mocapd_body_t b;
        mocapd_body(buf, i, &b);
        if (b.id != d->body || !(b.flags & MOCAPD_BODY_VALID)) continue;
        double x = b.pos[0], y = b.pos[1], tx = d->tx[d->k], ty = d->ty[d->k];
        double dist = hypot(tx - x, ty - y), v, w;
        if (d->settling > 0) { /* stopped, waiting out the delay and lag */
            send_command(d, 0.0, 0.0);
            if (--d->settling > 0) return 0;
            if (dist >= TOLERANCE_M) return 0; /* settled outside: drive on */
            printf("target %d (%.3f, %.3f): reached, error %.1f mm (pose t_ns %lld)\n",
                   d->k + 1, tx, ty, dist * 1000.0, (long long)h->t_ns);
            fflush(stdout);
            return ++d->k == d->n;
        }
        if (dist < TOLERANCE_M) {
            d->settling = SETTLE_PACKETS;
            send_command(d, 0.0, 0.0);
            return 0;
        }
        steer(x, y, yaw_of(b.quat), tx, ty, &v, &w);
        send_command(d, v, w);
    }
    return 0;
}

static void print_packet(const uint8_t *buf, const mocapd_header_t *h) {
    for (int i = 0; i < h->count; i++) {
        mocapd_body_t b;
        mocapd_body(buf, i, &b);
        printf("%u %lld %u %u %.9g %.9g %.9g %.9g %.9g %.9g %.9g %.9g\n", h->frame,
               (long long)h->t_ns, b.id, b.flags & MOCAPD_BODY_VALID, b.pos[0], b.pos[1],
               b.pos[2], b.quat[0], b.quat[1], b.quat[2], b.quat[3], yaw_of(b.quat));
    }
    fflush(stdout);
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: %s DEVICE [BAUD] [PACKETS]\n", argv[0]);
        return 2;
    }
    long baud = argc > 2 ? strtol(argv[2], NULL, 10) : 115200;
    long want = argc > 3 ? strtol(argv[3], NULL, 10) : 0;
    driver_t drive = {.sock = -1};
    if (argc > 6) { /* BODY PORT X,Y ...: drive */
        drive.body = (int)strtol(argv[4], NULL, 10);
        drive.to.sin_family = AF_INET;
        drive.to.sin_port = htons((uint16_t)strtol(argv[5], NULL, 10));
        drive.to.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        for (int a = 6; a < argc && drive.n < MAX_TARGETS; a++, drive.n++) {
            if (sscanf(argv[a], "%lf,%lf", &drive.tx[drive.n], &drive.ty[drive.n]) != 2) {
                fprintf(stderr, "goto_point: error: a target is X,Y in metres, got %s\n",
                        argv[a]);
                return 2;
            }
        }
        drive.sock = socket(AF_INET, SOCK_DGRAM, 0);
        if (drive.sock < 0) { perror("goto_point: socket"); return 1; }
    } else if (argc > 4) {
        fprintf(stderr, "usage: %s DEVICE BAUD 0 BODY PORT X,Y [X,Y ...]\n", argv[0]);
        return 2;
    }
    int fd = open_line(argv[1], baud);
    if (fd < 0) {
        fprintf(stderr, "goto_point: cannot open %s at %ld baud\n", argv[1], baud);
        return 1;
    }
    static uint8_t frame[MAX_FRAME], decoded[MAX_FRAME], chunk[512];
    size_t n = 0;
    long got = 0, bad = 0;
    int overflow = 0, done = 0;
    while ((want == 0 || got < want) && !done) {
        ssize_t r = read(fd, chunk, sizeof chunk);
        if (r <= 0) break;
        for (ssize_t k = 0; k < r && (want == 0 || got < want) && !done; k++) {
            if (chunk[k] != 0) {
                if (n < MAX_FRAME) frame[n++] = chunk[k];
                else overflow = 1;
                continue;
            }
            /* a frame ends: COBS, CRC, then the packet */
            size_t m = overflow ? 0 : mocapd_cobs_decode(frame, n, decoded);
            size_t len = m ? mocapd_check_crc(decoded, m) : 0;
            mocapd_header_t h;
            if (len && mocapd_parse(decoded, len, &h) >= 0) {
                if (drive.sock >= 0) done = drive_packet(&drive, decoded, &h);
                else print_packet(decoded, &h);
                got++;
            } else {
                bad++;
            }
            n = 0;
            overflow = 0;
        }
    }
    fprintf(stderr, "goto_point: %ld packets, %ld bad frames skipped\n", got, bad);
    close(fd);
    if (drive.sock >= 0) {
        send_command(&drive, 0.0, 0.0);
        close(drive.sock);
        return drive.k == drive.n ? 0 : 3;
    }
    return got > 0 ? 0 : 1;
}
