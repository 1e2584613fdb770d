/* kmea_pose.h: decode kmead's binary robot pose (Zenoh key <site>/robots/<robot>/pose).
 *
 * 56 bytes, little-endian, version 1 (docs/ros2.md, "Robots without ROS"). The decoder reads
 * the bytes one by one, so it works whatever the host's byte order and alignment (an ESP32,
 * an STM32, a PC); it refuses a message of another size or version (network input).
 * Units: metres, radians, seconds. C99, no allocation, no dependency but <stdint.h>.
 */
#ifndef KMEA_POSE_H
#define KMEA_POSE_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

#define KMEA_POSE_SIZE 56
#define KMEA_POSE_VERSION 1
#define KMEA_POSE_PREDICTED 0x1u /* t is the send time (kmead's filter.predict) */
#define KMEA_POSE_TRACKED 0x2u   /* sigmas from the tracking filter's covariance */
#define KMEA_POSE_STOPPING 0x4u  /* kmead stops (valid = 0) */

/* The message's fields in order; on the wire they are packed at the offsets given. */
struct kmea_pose {
    uint8_t version;      /*  0: 1 */
    uint8_t valid;        /*  1: 1 = a fix; 0 = stale, removed or kmead stopping */
    uint16_t flags;       /*  2: KMEA_POSE_* bits */
    uint32_t seq;         /*  4: this robot's message count */
    double t;             /*  8: s since the epoch, the time the pose refers to */
    float x, y;           /* 16, 20: m, world frame */
    float theta;          /* 24: rad in [-pi, pi) */
    float sigma_x;        /* 28: m, 1-sigma */
    float sigma_y;        /* 32: m */
    float sigma_theta;    /* 36: rad */
    float vx, vy;         /* 40, 44: m/s, world frame (0 when unknown) */
    float omega;          /* 48: rad/s */
    float age;            /* 52: s from the newest measurement to t */
};

static inline uint32_t kmea_le32_(const uint8_t *p) {
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

static inline float kmea_f32_(const uint8_t *p) {
    uint32_t u = kmea_le32_(p);
    float f;
    memcpy(&f, &u, sizeof f); /* IEEE 754 binary32 on every supported target */
    return f;
}

static inline double kmea_f64_(const uint8_t *p) {
    uint64_t u = (uint64_t)kmea_le32_(p) | (uint64_t)kmea_le32_(p + 4) << 32;
    double d;
    memcpy(&d, &u, sizeof d);
    return d;
}

/* 0 on success; -1 when buf is not one version-1 pose (then *out is untouched). */
static inline int kmea_pose_decode(const uint8_t *buf, size_t len, struct kmea_pose *out) {
    if (buf == NULL || out == NULL || len != KMEA_POSE_SIZE || buf[0] != KMEA_POSE_VERSION ||
        buf[1] > 1) {
        return -1;
    }
    out->version = buf[0];
    out->valid = buf[1];
    out->flags = (uint16_t)(buf[2] | buf[3] << 8);
    out->seq = kmea_le32_(buf + 4);
    out->t = kmea_f64_(buf + 8);
    out->x = kmea_f32_(buf + 16);
    out->y = kmea_f32_(buf + 20);
    out->theta = kmea_f32_(buf + 24);
    out->sigma_x = kmea_f32_(buf + 28);
    out->sigma_y = kmea_f32_(buf + 32);
    out->sigma_theta = kmea_f32_(buf + 36);
    out->vx = kmea_f32_(buf + 40);
    out->vy = kmea_f32_(buf + 44);
    out->omega = kmea_f32_(buf + 48);
    out->age = kmea_f32_(buf + 52);
    return 0;
}

#endif /* KMEA_POSE_H */
