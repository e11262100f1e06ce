/* goto_point.c: a robot's C side of mocapd's serial line: read the pose packets off a UART
 * (or the simulator's pseudo-terminal) with mocapd_packet.h and print every pose, as the
 * firmware of a robot would take its own pose before steering to a point.
 *
 *   cc -std=c99 -Wall -I daemon/publish -o goto_point examples/goto_point.c
 *   ./goto_point /dev/ttyUSB0 [BAUD] [PACKETS]
 *
 * Each line: frame t_ns body_id valid x y z qx qy qz qw yaw_rad (floats as %.9g, which
 * gives back the packet's float32 exactly). Frames that fail COBS or the CRC (the partial
 * one a reader starts in the middle of, a glitch) are counted and skipped; the count goes
 * to stderr at the end. Stops after PACKETS packets (0: never).
 */
#define _DEFAULT_SOURCE /* cfmakeraw */
#include <fcntl.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <termios.h>
#include <unistd.h>

#include "mocapd_packet.h"

#define MAX_FRAME 4096

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
    int fd = open_line(argv[1], baud);
    if (fd < 0) {
        fprintf(stderr, "goto_point: cannot open %s at %ld baud\n", argv[1], baud);
        return 1;
    }
    static uint8_t frame[MAX_FRAME], decoded[MAX_FRAME], chunk[512];
    size_t n = 0;
    long got = 0, bad = 0;
    int overflow = 0;
    while (want == 0 || got < want) {
        ssize_t r = read(fd, chunk, sizeof chunk);
        if (r <= 0) break;
        for (ssize_t k = 0; k < r && (want == 0 || got < want); k++) {
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
                print_packet(decoded, &h);
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
    return got > 0 ? 0 : 1;
}
