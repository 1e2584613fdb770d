/* kmea_pose_decode: read binary poses (56 bytes each) from stdin and print one line each.
 *
 *   cc -std=c99 -Wall -o kmea_pose_decode examples/kmea_pose_decode.c
 *   ./kmea_pose_decode < poses.bin
 *
 * A zenoh-pico subscriber on "<site>/robots/<robot>/pose" calls kmea_pose_decode() on each
 * sample's payload the same way. Exit status 1 if any message was refused.
 */
#include <stdio.h>

#include "kmea_pose.h"

int main(void) {
    uint8_t buf[KMEA_POSE_SIZE];
    int bad = 0;
    size_t n;
    while ((n = fread(buf, 1, sizeof buf, stdin)) > 0) {
        struct kmea_pose p;
        if (kmea_pose_decode(buf, n, &p) != 0) {
            fprintf(stderr, "refused: %zu bytes, version %u\n", n, n ? buf[0] : 0u);
            bad = 1;
            continue;
        }
        printf("seq=%lu t=%.6f valid=%u flags=%u x=%.6f y=%.6f theta=%.6f "
               "sigma_x=%.6f sigma_y=%.6f sigma_theta=%.6f vx=%.6f vy=%.6f omega=%.6f "
               "age=%.6f\n",
               (unsigned long)p.seq, p.t, p.valid, p.flags, p.x, p.y, p.theta, p.sigma_x,
               p.sigma_y, p.sigma_theta, p.vx, p.vy, p.omega, p.age);
    }
    return bad;
}
