/* The rays of `cargo bench --bench rays` traced with Embree: a reference for how fast a
 * production CPU kernel traces Sponza's gather rays on this machine, beside `Accel`.
 *
 *   cargo bench --bench rays -- benches/sponza/job.json --dump /tmp/rays
 *   cc -O2 benches/embree_trace.c -lembree3 -lm -o /tmp/embree_trace && /tmp/embree_trace /tmp/rays
 *
 * Needs Embree 3's headers and library (Debian 12: `apt install libembree-dev`, 3.13.5);
 * anchorage does not link it. The static and the dynamic triangles are two geometries of one
 * scene, built at RTC_BUILD_QUALITY_HIGH on one thread, once with RTC_SCENE_FLAG_ROBUST (a
 * watertight test and traversal, as `Accel`'s) and once without. Each is timed on one thread
 * (the best of three rounds): every ray to its closest hit with rtcIntersect1, the same rays
 * four at a time as the gather packs them (2 x 2 neighbouring strata) with rtcIntersect4,
 * and the rays cut to a tenth of the scene's radius with rtcOccluded1. Its hits are compared
 * with `Accel::closest`'s: how many name another triangle, how many of those lie at a
 * distance within 1e-5 of ours (ties and near-ties), and how many rays one of the two lets
 * escape where the other hits.
 *
 * Files (little-endian, written by the rays bench): static.bin and dynamic.bin, nine f32 a
 * triangle; rays.bin, origin and direction as six f32 a ray; packets.bin, four i32 ray
 * indices a packet (-1: an empty lane); hits.bin, per ray the distance (f32, infinite on a
 * miss), the set (i32: 0 static, 1 dynamic, -1 none) and the triangle (i32); short.bin, the
 * shadow rays' length (f32).
 */
#include <embree3/rtcore.h>
#include <math.h>
#include <pmmintrin.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <xmmintrin.h>

static void *slurp(const char *dir, const char *name, long *bytes) {
    char path[4096];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    FILE *f = fopen(path, "rb");
    if (!f) {
        perror(path);
        exit(2);
    }
    fseek(f, 0, SEEK_END);
    *bytes = ftell(f);
    fseek(f, 0, SEEK_SET);
    void *data = malloc(*bytes ? *bytes : 1);
    if (fread(data, 1, *bytes, f) != (size_t)*bytes) {
        perror(path);
        exit(2);
    }
    fclose(f);
    return data;
}

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + t.tv_nsec * 1e-9;
}

struct Hit {
    float t;
    int set;
    int triangle;
};

static void add_triangles(RTCDevice dev, RTCScene scene, const float *v, long n) {
    if (n == 0)
        return;
    RTCGeometry g = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_TRIANGLE);
    float *vb = rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                        3 * sizeof(float), 3 * n);
    unsigned *ib = rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                           3 * sizeof(unsigned), n);
    memcpy(vb, v, 9 * n * sizeof(float));
    for (long i = 0; i < 3 * n; i++)
        ib[i] = (unsigned)i;
    rtcSetGeometryBuildQuality(g, RTC_BUILD_QUALITY_HIGH);
    rtcCommitGeometry(g);
    rtcAttachGeometry(scene, g);
    rtcReleaseGeometry(g);
}

int main(int argc, char **argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: %s DIR (written by the rays bench's --dump)\n", argv[0]);
        return 2;
    }
    const char *dir = argv[1];
    _MM_SET_FLUSH_ZERO_MODE(_MM_FLUSH_ZERO_ON);
    _MM_SET_DENORMALS_ZERO_MODE(_MM_DENORMALS_ZERO_ON);
    long ns, nd, nr, np, nh, nshort;
    float *statics = slurp(dir, "static.bin", &ns);
    float *dynamics = slurp(dir, "dynamic.bin", &nd);
    float *rays = slurp(dir, "rays.bin", &nr);
    int *packets = slurp(dir, "packets.bin", &np);
    struct Hit *ours = slurp(dir, "hits.bin", &nh);
    float *shortp = slurp(dir, "short.bin", &nshort);
    ns /= 36, nd /= 36, nr /= 24, np /= 16, nh /= 12;
    if (nh != nr || nshort != 4) {
        fprintf(stderr, "%s: hits.bin or short.bin does not match rays.bin\n", dir);
        return 2;
    }
    float shadow = *shortp;
    RTCDevice dev = rtcNewDevice("threads=1");
    if (!dev) {
        fprintf(stderr, "cannot create an Embree device\n");
        return 2;
    }
    long version = rtcGetDeviceProperty(dev, RTC_DEVICE_PROPERTY_VERSION);
    printf("%s: %ld static and %ld dynamic triangles, %ld gather rays; Embree %ld.%ld.%ld, 1 thread\n",
           dir, ns, nd, nr, version / 10000, version / 100 % 100, version % 100);
    int *triangle = malloc(nr * sizeof(int)), *set = malloc(nr * sizeof(int));
    float *dist = malloc(nr * sizeof(float));
    for (int robust = 1; robust >= 0; robust--) {
        RTCScene scene = rtcNewScene(dev);
        rtcSetSceneFlags(scene, robust ? RTC_SCENE_FLAG_ROBUST : RTC_SCENE_FLAG_NONE);
        rtcSetSceneBuildQuality(scene, RTC_BUILD_QUALITY_HIGH);
        add_triangles(dev, scene, statics, ns);
        add_triangles(dev, scene, dynamics, nd);
        double t0 = now();
        rtcCommitScene(scene);
        double build = now() - t0;
        double one = INFINITY, four = INFINITY, occl = INFINITY;
        long blocked = 0;
        for (int round = 0; round < 3; round++) {
            struct RTCIntersectContext ctx;
            rtcInitIntersectContext(&ctx);
            t0 = now();
            for (long r = 0; r < nr; r++) {
                const float *R = rays + 6 * r;
                struct RTCRayHit rh = {0};
                rh.ray.org_x = R[0], rh.ray.org_y = R[1], rh.ray.org_z = R[2];
                rh.ray.dir_x = R[3], rh.ray.dir_y = R[4], rh.ray.dir_z = R[5];
                rh.ray.tnear = 0.0f, rh.ray.tfar = INFINITY, rh.ray.mask = -1;
                rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
                rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
                rtcIntersect1(scene, &ctx, &rh);
                int hit = rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
                /* geometry 0 is the static set unless it is empty */
                set[r] = hit ? (ns == 0 ? 1 : (int)rh.hit.geomID) : -1;
                triangle[r] = hit ? (int)rh.hit.primID : -1;
                dist[r] = hit ? rh.ray.tfar : INFINITY;
            }
            double s = now() - t0;
            one = s < one ? s : one;
            t0 = now();
            for (long p = 0; p < np; p++) {
                struct RTCRayHit4 rh;
                int valid[4];
                for (int l = 0; l < 4; l++) {
                    int i = packets[4 * p + l];
                    const float *R = rays + 6 * (i >= 0 ? i : 0);
                    valid[l] = i >= 0 ? -1 : 0;
                    rh.ray.org_x[l] = R[0], rh.ray.org_y[l] = R[1], rh.ray.org_z[l] = R[2];
                    rh.ray.dir_x[l] = R[3], rh.ray.dir_y[l] = R[4], rh.ray.dir_z[l] = R[5];
                    rh.ray.tnear[l] = 0.0f, rh.ray.tfar[l] = INFINITY;
                    rh.ray.mask[l] = -1, rh.ray.flags[l] = 0, rh.ray.time[l] = 0.0f;
                    rh.hit.geomID[l] = RTC_INVALID_GEOMETRY_ID;
                    rh.hit.instID[0][l] = RTC_INVALID_GEOMETRY_ID;
                }
                rtcIntersect4(valid, scene, &ctx, &rh);
            }
            s = now() - t0;
            four = s < four ? s : four;
            blocked = 0;
            t0 = now();
            for (long r = 0; r < nr; r++) {
                const float *R = rays + 6 * r;
                struct RTCRay ray = {0};
                ray.org_x = R[0], ray.org_y = R[1], ray.org_z = R[2];
                ray.dir_x = R[3], ray.dir_y = R[4], ray.dir_z = R[5];
                ray.tnear = 0.0f, ray.tfar = shadow, ray.mask = -1;
                rtcOccluded1(scene, &ctx, &ray);
                blocked += ray.tfar < 0.0f;
            }
            s = now() - t0;
            occl = s < occl ? s : occl;
        }
        long differ = 0, near = 0, escaped_here = 0, escaped_ours = 0;
        for (long r = 0; r < nr; r++) {
            if (set[r] == ours[r].set && triangle[r] == ours[r].triangle)
                continue;
            differ++;
            if (set[r] < 0)
                escaped_here++;
            else if (ours[r].set < 0)
                escaped_ours++;
            else if (fabsf(dist[r] - ours[r].t) <= 1e-5f * ours[r].t)
                near++;
        }
        printf("%-8s build %.2f s | closest hit: rtcIntersect1 %.3f M/s, rtcIntersect4 over 2x2 "
               "strata %.3f M/s; %ld hits differ from Accel::closest's (%ld within 1e-5 of its "
               "distance, %ld escape here, %ld escape ours) | shadow rays of %.3f: rtcOccluded1 "
               "%.3f M/s, %ld blocked\n",
               robust ? "robust" : "default", build, nr / one / 1e6, nr / four / 1e6, differ,
               near, escaped_here, escaped_ours, shadow, nr / occl / 1e6, blocked);
        rtcReleaseScene(scene);
    }
    rtcReleaseDevice(dev);
    return 0;
}
