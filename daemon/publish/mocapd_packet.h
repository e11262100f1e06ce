/* mocapd_packet.h: decode mocapd pose packets on a microcontroller or in C.
 *
 * The layout is docs/protocol.md: little-endian, packed, a 24-byte header and 36 bytes per
 * rigid body; when header flag MOCAPD_HAS_MARKERS is set (a marker set is configured), a
 * 4-byte section header and 16 bytes per labelled marker follow the bodies. Over UDP a datagram is one packet. Over serial a packet is followed by its
 * CRC-16/CCITT-FALSE (little-endian) and COBS-encoded, each frame ending in a 0x00 byte
 * (Arduino PacketSerial's default framing: its onPacketReceived gets the COBS-decoded
 * bytes; pass them to mocapd_check_crc).
 *
 * Header only, no allocation, C99. Assumes a little-endian CPU with IEEE-754 floats (every
 * Arduino, ESP32, STM32 and x86); on others, decode the fields byte by byte.
 */
#ifndef MOCAPD_PACKET_H
#define MOCAPD_PACKET_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

#define MOCAPD_MAGIC 0x434Du   /* "MC" */
#define MOCAPD_VERSION 1u
#define MOCAPD_BODY_VALID 0x01u
#define MOCAPD_HAS_MARKERS 0x01u  /* header flag: the labelled-markers section follows */

#pragma pack(push, 1)
typedef struct {
    uint16_t magic;      /* MOCAPD_MAGIC */
    uint8_t version;     /* MOCAPD_VERSION */
    uint8_t count;       /* bodies that follow */
    uint32_t frame;      /* frame number */
    int64_t t_ns;        /* capture time, ns, the daemon's monotonic clock */
    uint32_t latency_ns; /* frame arrival to packet encoding in the daemon */
    uint32_t flags;      /* bit 0: MOCAPD_HAS_MARKERS; other bits 0 */
} mocapd_header_t;

typedef struct {
    uint16_t id;         /* streaming id from the configuration */
    uint8_t flags;       /* bit 0: tracking valid; when clear the pose fields are NaN */
    uint8_t markers;     /* markers used for the pose */
    float pos[3];        /* x, y, z, metres, world frame (z up) */
    float quat[4];       /* x, y, z, w */
    float error_m;       /* mean marker fit error, metres */
} mocapd_body_t;

typedef struct {
    uint16_t count;      /* labelled markers that follow */
    uint16_t set_size;   /* markers in the marker set (indices are below this) */
} mocapd_markers_header_t;

typedef struct {
    uint16_t index;      /* the marker's index in the marker set (its name's position) */
    uint8_t confidence;  /* 0-255 for the labeller's confidence 0..1 */
    uint8_t flags;       /* reserved, 0 */
    float pos[3];        /* x, y, z, metres, world frame (z up) */
} mocapd_marker_t;
#pragma pack(pop)

typedef char mocapd_header_size_check[sizeof(mocapd_header_t) == 24 ? 1 : -1];
typedef char mocapd_body_size_check[sizeof(mocapd_body_t) == 36 ? 1 : -1];
typedef char mocapd_markers_header_size_check[sizeof(mocapd_markers_header_t) == 4 ? 1 : -1];
typedef char mocapd_marker_size_check[sizeof(mocapd_marker_t) == 16 ? 1 : -1];

/* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF. */
static inline uint16_t mocapd_crc16(const uint8_t *data, size_t len) {
    uint16_t crc = 0xFFFFu;
    for (size_t i = 0; i < len; i++) {
        crc ^= (uint16_t)data[i] << 8;
        for (int b = 0; b < 8; b++)
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
    }
    return crc;
}

/* COBS-decode `len` bytes (without the 0x00 delimiter) into out; returns the decoded
 * length, or 0 on a malformed frame. out may not overlap in; out needs len bytes. */
static inline size_t mocapd_cobs_decode(const uint8_t *in, size_t len, uint8_t *out) {
    size_t i = 0, o = 0;
    while (i < len) {
        uint8_t code = in[i];
        if (code == 0 || i + code > len) return 0;
        memcpy(out + o, in + i + 1, (size_t)code - 1);
        o += (size_t)code - 1;
        i += code;
        if (code < 0xFF && i < len) out[o++] = 0;
    }
    return o;
}

/* A decoded serial frame: check and strip its CRC; returns the payload length or 0. */
static inline size_t mocapd_check_crc(const uint8_t *buf, size_t len) {
    if (len < 2) return 0;
    uint16_t got = (uint16_t)(buf[len - 2] | ((uint16_t)buf[len - 1] << 8));
    return mocapd_crc16(buf, len - 2) == got ? len - 2 : 0;
}

/* Validate a packet; returns its body count, or -1 if it is not a whole mocapd packet. */
static inline int mocapd_parse(const uint8_t *buf, size_t len, mocapd_header_t *header) {
    if (len < sizeof(mocapd_header_t)) return -1;
    memcpy(header, buf, sizeof(mocapd_header_t));
    if (header->magic != MOCAPD_MAGIC || header->version != MOCAPD_VERSION) return -1;
    size_t end = sizeof(mocapd_header_t) + (size_t)header->count * sizeof(mocapd_body_t);
    if (header->flags & MOCAPD_HAS_MARKERS) {
        mocapd_markers_header_t mh;
        if (len < end + sizeof(mh)) return -1;
        memcpy(&mh, buf + end, sizeof(mh));
        if (len != end + sizeof(mh) + (size_t)mh.count * sizeof(mocapd_marker_t)) return -1;
    } else if (len != end) {
        return -1;
    }
    return header->count;
}

/* Labelled markers in a validated packet (0 when it has no marker section); the set's
 * size goes to *set_size when that is not NULL. */
static inline int mocapd_marker_count(const uint8_t *buf, const mocapd_header_t *header,
                                      uint16_t *set_size) {
    mocapd_markers_header_t mh = {0, 0};
    if (header->flags & MOCAPD_HAS_MARKERS)
        memcpy(&mh, buf + sizeof(mocapd_header_t) + (size_t)header->count *
               sizeof(mocapd_body_t), sizeof(mh));
    if (set_size) *set_size = mh.set_size;
    return mh.count;
}

/* Copy labelled marker i (0 <= i < mocapd_marker_count) out of a validated packet. */
static inline void mocapd_marker(const uint8_t *buf, const mocapd_header_t *header, int i,
                                 mocapd_marker_t *marker) {
    memcpy(marker, buf + sizeof(mocapd_header_t) + (size_t)header->count *
           sizeof(mocapd_body_t) + sizeof(mocapd_markers_header_t) +
           (size_t)i * sizeof(mocapd_marker_t), sizeof(mocapd_marker_t));
}

/* Copy body i (0 <= i < count) out of a validated packet. */
static inline void mocapd_body(const uint8_t *buf, int i, mocapd_body_t *body) {
    memcpy(body, buf + sizeof(mocapd_header_t) + (size_t)i * sizeof(mocapd_body_t),
           sizeof(mocapd_body_t));
}

#endif /* MOCAPD_PACKET_H */
