// Ray throughput of torch_rbpt's BVH (csrc/bvh.cpp, linked directly, no torch) against
// Embree 3 on the same mesh and the same rays, in the same process.
//
// Built and run by benchmarks/bench_rays.py, which writes the input file:
//   char magic[8] = "RBRAYS1\0"; uint32 vertex_count, triangle_count, set_count;
//   float32 vertices[vertex_count][3]; uint32 triangles[triangle_count][3];
//   per ray set: char name[16] (NUL padded); uint32 n; float32 origins[n][3];
//                float32 directions[n][3] (unit length).
//
//   bench_rays INPUT [--threads 1,2] [--repeats 3] [--no-embree]
//
// Prints one line per measurement, "KEY key=value ...", for the script to parse:
//   BUILD impl=... ms=...                 (best of the repeats)
//   TRACE set=... query=closest|any impl=ours|embree1|embree4|embree8 threads=T mrays=...
//   CHECK set=... query=... ref=... n=... ref_hits=... mismatches=... hit_miss=... t_diff=... prim_diff=...
//   MISMATCH ...                          (the first few mismatching rays, for diagnosis)
// Without HAVE_EMBREE (no Embree 3 headers) only our BVH is measured.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <string>
#include <thread>
#include <vector>

#include "bvh.h"
#include "shapes.h"

#ifdef HAVE_EMBREE
#include <embree3/rtcore.h>
#endif

using rbpt::BVH;
using rbpt::Geometry;
using rbpt::Hit;
using rbpt::Ray;
using rbpt::Vec3;

namespace {

struct RaySet {
    std::string name;
    std::vector<float> o, d;  // n x 3 each
    size_t size() const { return o.size() / 3; }
};

/// Result of one ray: t (inf on a miss) and the triangle hit (~0u on a miss).
struct Result {
    float t = INFINITY;
    uint32_t prim = ~0u;
};

[[noreturn]] void die(const std::string &msg) {
    std::fprintf(stderr, "bench_rays: %s\n", msg.c_str());
    std::exit(2);
}

void read_input(const char *path, std::vector<float> &vertices, std::vector<uint32_t> &triangles,
                std::vector<RaySet> &sets) {
    FILE *f = std::fopen(path, "rb");
    if (!f) die(std::string("cannot open ") + path);
    auto read = [&](void *p, size_t bytes) {
        if (bytes && std::fread(p, 1, bytes, f) != bytes) die(std::string("truncated file ") + path);
    };
    char magic[8];
    read(magic, 8);
    if (std::memcmp(magic, "RBRAYS1", 8) != 0) die(std::string("not a ray file: ") + path);
    uint32_t nv, nt, ns;
    read(&nv, 4);
    read(&nt, 4);
    read(&ns, 4);
    vertices.resize(size_t(nv) * 3);
    triangles.resize(size_t(nt) * 3);
    read(vertices.data(), vertices.size() * 4);
    read(triangles.data(), triangles.size() * 4);
    for (uint32_t v : triangles)
        if (v >= nv) die("triangle index out of range");
    sets.resize(ns);
    for (RaySet &s : sets) {
        char name[17] = {};
        read(name, 16);
        s.name = name;
        uint32_t n;
        read(&n, 4);
        s.o.resize(size_t(n) * 3);
        s.d.resize(size_t(n) * 3);
        read(s.o.data(), s.o.size() * 4);
        read(s.d.data(), s.d.size() * 4);
    }
    std::fclose(f);
}

double now() {
    return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

/// Run body(begin, end) over [0, n) in chunks handed out to `threads` std::threads.
void parallel_chunks(size_t n, int threads, size_t chunk, const std::function<void(size_t, size_t)> &body) {
    std::atomic<size_t> next{0};
    auto worker = [&] {
        for (;;) {
            size_t begin = next.fetch_add(chunk);
            if (begin >= n) return;
            body(begin, std::min(n, begin + chunk));
        }
    };
    std::vector<std::thread> pool;
    for (int i = 1; i < threads; ++i) pool.emplace_back(worker);
    worker();
    for (std::thread &t : pool) t.join();
}

Ray make_ray(const RaySet &s, size_t i) {
    Ray ray;
    ray.o = {s.o[3 * i], s.o[3 * i + 1], s.o[3 * i + 2]};
    ray.d = {s.d[3 * i], s.d[3 * i + 1], s.d[3 * i + 2]};
    return ray;
}

#ifdef HAVE_EMBREE
void init_ray1(RTCRayHit &rh, const RaySet &s, size_t i) {
    rh.ray.org_x = s.o[3 * i];
    rh.ray.org_y = s.o[3 * i + 1];
    rh.ray.org_z = s.o[3 * i + 2];
    rh.ray.dir_x = s.d[3 * i];
    rh.ray.dir_y = s.d[3 * i + 1];
    rh.ray.dir_z = s.d[3 * i + 2];
    rh.ray.tnear = 0.f;
    rh.ray.tfar = INFINITY;
    rh.ray.time = 0.f;
    rh.ray.mask = ~0u;
    rh.ray.id = 0;
    rh.ray.flags = 0;
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
}

/// Closest hits with rtcIntersectW (W = 4 or 8) over packets of consecutive rays.
template <int W, typename RayHitW, typename Fn>
void embree_packets(RTCScene scene, const RaySet &s, size_t begin, size_t end, Result *out, Fn intersect) {
    alignas(64) RayHitW rh;
    alignas(64) int valid[W];
    RTCIntersectContext ctx;
    for (size_t i = begin; i < end; i += W) {
        rtcInitIntersectContext(&ctx);
        for (int k = 0; k < W; ++k) {
            size_t j = std::min(i + k, end - 1);
            valid[k] = i + k < end ? -1 : 0;
            rh.ray.org_x[k] = s.o[3 * j];
            rh.ray.org_y[k] = s.o[3 * j + 1];
            rh.ray.org_z[k] = s.o[3 * j + 2];
            rh.ray.dir_x[k] = s.d[3 * j];
            rh.ray.dir_y[k] = s.d[3 * j + 1];
            rh.ray.dir_z[k] = s.d[3 * j + 2];
            rh.ray.tnear[k] = 0.f;
            rh.ray.tfar[k] = INFINITY;
            rh.ray.time[k] = 0.f;
            rh.ray.mask[k] = ~0u;
            rh.ray.id[k] = 0;
            rh.ray.flags[k] = 0;
            rh.hit.geomID[k] = RTC_INVALID_GEOMETRY_ID;
            rh.hit.instID[0][k] = RTC_INVALID_GEOMETRY_ID;
        }
        intersect(valid, scene, &ctx, &rh);
        for (int k = 0; k < W && i + k < end; ++k) {
            bool hit = rh.hit.geomID[k] != RTC_INVALID_GEOMETRY_ID;
            out[i + k] = hit ? Result{rh.ray.tfar[k], rh.hit.primID[k]} : Result{};
        }
    }
}
#endif

/// Compares two result arrays: hit/miss, t to 1e-4 relative, and the triangle (information
/// only: two triangles sharing an edge may both be "the" hit).
void check(const RaySet &s, const char *query, const std::vector<Result> &ours,
           const std::vector<Result> &ref, const char *ref_name) {
    size_t hit_miss = 0, t_diff = 0, prim_diff = 0, shown = 0, hits = 0;
    for (size_t i = 0; i < ours.size(); ++i) {
        const Result &a = ours[i], &b = ref[i];
        bool ha = a.prim != ~0u, hb = b.prim != ~0u;
        bool bad = false;
        hits += hb;
        if (ha != hb) {
            ++hit_miss;
            bad = true;
        } else if (ha) {
            if (std::abs(a.t - b.t) > 1e-4f * std::max(std::abs(b.t), 1e-30f)) {
                ++t_diff;
                bad = true;
            } else if (a.prim != b.prim) {
                ++prim_diff;
            }
        }
        if (bad && shown < 5) {
            ++shown;
            std::printf("MISMATCH set=%s query=%s ref=%s ray=%zu o=%.9g,%.9g,%.9g d=%.9g,%.9g,%.9g "
                        "ours_t=%.9g ours_prim=%d ref_t=%.9g ref_prim=%d\n",
                        s.name.c_str(), query, ref_name, i, s.o[3 * i], s.o[3 * i + 1], s.o[3 * i + 2],
                        s.d[3 * i], s.d[3 * i + 1], s.d[3 * i + 2], a.t, int(a.prim), b.t, int(b.prim));
        }
    }
    std::printf("CHECK set=%s query=%s ref=%s n=%zu ref_hits=%zu mismatches=%zu hit_miss=%zu t_diff=%zu "
                "prim_diff=%zu\n",
                s.name.c_str(), query, ref_name, ours.size(), hits, hit_miss + t_diff, hit_miss, t_diff, prim_diff);
}

}  // namespace

int main(int argc, char **argv) {
    if (argc < 2) die("usage: bench_rays INPUT [--threads 1,2] [--repeats 3] [--no-embree]");
    std::vector<int> thread_counts = {1, 2};
    int repeats = 3;
    bool use_embree = true;
    for (int i = 2; i < argc; ++i) {
        std::string a = argv[i];
        if (a == "--threads" && i + 1 < argc) {
            thread_counts.clear();
            std::string list = argv[++i];
            for (size_t p = 0; p < list.size();) {
                size_t q = list.find(',', p);
                if (q == std::string::npos) q = list.size();
                thread_counts.push_back(std::atoi(list.substr(p, q - p).c_str()));
                p = q + 1;
            }
        } else if (a == "--repeats" && i + 1 < argc) {
            repeats = std::max(1, std::atoi(argv[++i]));
        } else if (a == "--no-embree") {
            use_embree = false;
        } else {
            die("unknown argument " + a);
        }
    }
#ifndef HAVE_EMBREE
    use_embree = false;
#endif
    std::vector<float> vertices;
    std::vector<uint32_t> triangles;
    std::vector<RaySet> sets;
    read_input(argv[1], vertices, triangles, sets);
    const size_t nt = triangles.size() / 3;
    std::printf("INFO vertices=%zu triangles=%zu embree=%d\n", vertices.size() / 3, nt, int(use_embree));

    // Our geometry: one mesh shape over every triangle.
    Geometry geometry;
    geometry.positions.resize(vertices.size() / 3);
    for (size_t i = 0; i < geometry.positions.size(); ++i)
        geometry.positions[i] = {vertices[3 * i], vertices[3 * i + 1], vertices[3 * i + 2]};
    geometry.triangles.resize(nt);
    for (size_t i = 0; i < nt; ++i)
        geometry.triangles[i] = {{triangles[3 * i], triangles[3 * i + 1], triangles[3 * i + 2]}, 0};
    rbpt::Shape shape;
    shape.tri_begin = 0;
    shape.tri_count = uint32_t(nt);
    geometry.shapes.push_back(shape);
    geometry.prepare();

    // Build (single-threaded, as in the renderer); best of the repeats.
    BVH bvh;
    double best = INFINITY;
    for (int r = 0; r < repeats; ++r) {
        double start = now();
        bvh.build(geometry);
        best = std::min(best, now() - start);
    }
    std::printf("BUILD impl=ours threads=1 ms=%.3f nodes=%zu\n", best * 1e3, bvh.node_count());

#ifdef HAVE_EMBREE
    RTCDevice device = nullptr;
    RTCScene escene = nullptr;
    if (use_embree) {
        // Build time with Embree's own thread pool (all cores), then on one thread (as ours).
        // Rays are traced on the latter's scene, so that no idle pool threads compete with
        // the tracing threads (the build thread count does not change Embree's tree).
        for (int pass = 0; pass < 2; ++pass) {
            RTCDevice dev = rtcNewDevice(pass == 1 ? "threads=1" : nullptr);
            if (!dev) die("rtcNewDevice failed");
            double best_e = INFINITY;
            for (int r = 0; r < repeats; ++r) {
                double start = now();
                RTCScene sc = rtcNewScene(dev);
                rtcSetSceneFlags(sc, RTC_SCENE_FLAG_NONE);
                rtcSetSceneBuildQuality(sc, RTC_BUILD_QUALITY_MEDIUM);
                RTCGeometry geom = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_TRIANGLE);
                float *vb = static_cast<float *>(rtcSetNewGeometryBuffer(
                    geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), vertices.size() / 3));
                std::memcpy(vb, vertices.data(), vertices.size() * sizeof(float));
                uint32_t *ib = static_cast<uint32_t *>(rtcSetNewGeometryBuffer(
                    geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(uint32_t), nt));
                std::memcpy(ib, triangles.data(), triangles.size() * sizeof(uint32_t));
                rtcCommitGeometry(geom);
                rtcAttachGeometry(sc, geom);
                rtcReleaseGeometry(geom);
                rtcCommitScene(sc);
                best_e = std::min(best_e, now() - start);
                if (pass == 1 && r == repeats - 1) {
                    device = dev;
                    escene = sc;
                } else {
                    rtcReleaseScene(sc);
                }
            }
            std::printf("BUILD impl=embree threads=%s ms=%.3f\n", pass == 1 ? "1" : "all", best_e * 1e3);
            if (pass == 1)
                std::printf("INFO embree_version=%ld\n", long(rtcGetDeviceProperty(dev, RTC_DEVICE_PROPERTY_VERSION)));
            if (pass == 0) rtcReleaseDevice(dev);
        }
    }
#endif

    const size_t chunk = 4096;
    for (const RaySet &s : sets) {
        const size_t n = s.size();
        std::vector<Result> ours(n), ours_any(n), ref(n), ref_any(n), ref4(n), ref8(n);
        // The measurements: (query, impl, per-chunk work).
        struct Measurement {
            const char *query, *impl;
            std::function<void(size_t, size_t)> body;
        };
        std::vector<Measurement> ms;
        ms.push_back({"closest", "ours", [&](size_t b, size_t e) {
                          for (size_t i = b; i < e; ++i) {
                              Hit hit;
                              ours[i] = bvh.intersect(make_ray(s, i), &hit) ? Result{hit.t, hit.prim} : Result{};
                          }
                      }});
        ms.push_back({"any", "ours", [&](size_t b, size_t e) {
                          for (size_t i = b; i < e; ++i)
                              ours_any[i] = bvh.occluded(make_ray(s, i)) ? Result{0.f, 0u} : Result{};
                      }});
#ifdef HAVE_EMBREE
        if (use_embree) {
            ms.push_back({"closest", "embree1", [&](size_t b, size_t e) {
                              RTCIntersectContext ctx;
                              RTCRayHit rh;
                              for (size_t i = b; i < e; ++i) {
                                  rtcInitIntersectContext(&ctx);
                                  init_ray1(rh, s, i);
                                  rtcIntersect1(escene, &ctx, &rh);
                                  bool hit = rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
                                  ref[i] = hit ? Result{rh.ray.tfar, rh.hit.primID} : Result{};
                              }
                          }});
            ms.push_back({"any", "embree1", [&](size_t b, size_t e) {
                              RTCIntersectContext ctx;
                              RTCRayHit rh;
                              for (size_t i = b; i < e; ++i) {
                                  rtcInitIntersectContext(&ctx);
                                  init_ray1(rh, s, i);
                                  rtcOccluded1(escene, &ctx, &rh.ray);
                                  // rtcOccluded1 sets tfar to -inf when something blocks the ray.
                                  ref_any[i] = rh.ray.tfar < 0.f ? Result{0.f, 0u} : Result{};
                              }
                          }});
            ms.push_back({"closest", "embree4", [&](size_t b, size_t e) {
                              embree_packets<4, RTCRayHit4>(escene, s, b, e, ref4.data(), rtcIntersect4);
                          }});
            ms.push_back({"closest", "embree8", [&](size_t b, size_t e) {
                              embree_packets<8, RTCRayHit8>(escene, s, b, e, ref8.data(), rtcIntersect8);
                          }});
        }
#endif
        for (int threads : thread_counts) {
            // Interleave the implementations within each repeat, so that load from other
            // processes on a shared machine hits them alike; keep the best time of each.
            std::vector<double> best_t(ms.size(), INFINITY);
            for (int r = 0; r < repeats; ++r) {
                for (size_t k = 0; k < ms.size(); ++k) {
                    double start = now();
                    parallel_chunks(n, threads, chunk, ms[k].body);
                    best_t[k] = std::min(best_t[k], now() - start);
                }
            }
            for (size_t k = 0; k < ms.size(); ++k)
                std::printf("TRACE set=%s query=%s impl=%s threads=%d mrays=%.4f\n", s.name.c_str(),
                            ms[k].query, ms[k].impl, threads, n / best_t[k] / 1e6);
            std::fflush(stdout);
        }
        // Ours closest against ours any-hit (self-consistency), then against Embree.
        {
            std::vector<Result> hit_only(n);
            for (size_t i = 0; i < n; ++i) hit_only[i] = ours[i].prim != ~0u ? Result{0.f, 0u} : Result{};
            check(s, "any", ours_any, hit_only, "ours_closest");
        }
#ifdef HAVE_EMBREE
        if (use_embree) {
            check(s, "closest", ours, ref, "embree1");
            check(s, "any", ours_any, ref_any, "embree1");
            check(s, "closest", ref4, ref, "embree4_vs_embree1");
            check(s, "closest", ref8, ref, "embree8_vs_embree1");
        }
#endif
        std::fflush(stdout);
    }
#ifdef HAVE_EMBREE
    if (escene) rtcReleaseScene(escene);
    if (device) rtcReleaseDevice(device);
#endif
    return 0;
}
