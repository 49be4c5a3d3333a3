// Mitsuba 3 creates its Embree device with a configuration of its own ("threads=N,
// user_threads=N"), so Embree picks its instruction set at run time: AVX-512 where the CPU
// has it. Preloaded into a benchmark's process (LD_PRELOAD; mitsuba_ref.limit_embree builds
// and preloads it), this library puts itself in front of Mitsuba's rtcNewDevice and appends
// max_isa=$RBPT_EMBREE_MAX_ISA to that configuration, so that Mitsuba's rays are cast as on
// a CPU without AVX-512 (the benchmarks' AVX2 setting). The real function is looked up in
// Mitsuba's Embree library, $RBPT_EMBREE_LIB; the configuration passed on is left in
// $RBPT_EMBREE_CONFIG for the benchmark's report.
#include <dlfcn.h>

#include <cstdio>
#include <cstdlib>
#include <string>

namespace mitsuba {
struct RTCDeviceTy;
RTCDeviceTy *rtcNewDevice(const char *config);
}  // namespace mitsuba

mitsuba::RTCDeviceTy *mitsuba::rtcNewDevice(const char *config) {
    using NewDevice = RTCDeviceTy *(*)(const char *);
    const char *lib = std::getenv("RBPT_EMBREE_LIB"), *isa = std::getenv("RBPT_EMBREE_MAX_ISA");
    void *handle = lib && *lib ? dlopen(lib, RTLD_NOW | RTLD_NOLOAD) : nullptr;
    NewDevice real = handle ? reinterpret_cast<NewDevice>(dlsym(handle, "_ZN7mitsuba12rtcNewDeviceEPKc")) : nullptr;
    if (!real || real == &mitsuba::rtcNewDevice) {  // (not loaded, or this very function)
        std::fprintf(stderr, "embree_max_isa: no mitsuba::rtcNewDevice in RBPT_EMBREE_LIB=%s\n", lib ? lib : "(unset)");
        std::abort();
    }
    std::string c = config ? config : "";
    if (isa && *isa) c += (c.empty() ? "max_isa=" : ",max_isa=") + std::string(isa);
    setenv("RBPT_EMBREE_CONFIG", c.c_str(), 1);
    return real(c.c_str());
}
