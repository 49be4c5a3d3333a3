// Small vector math for the renderer core: geometry in float (Vec2, Vec3, Frame, Ray) and the
// RGB spectrum type that the path tracer is templated on.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>

/// For the small helpers that the integrators call once per vertex (BSDF and emitter dispatch,
/// ray spawning, warps): GCC's size heuristics leave them out of the large path loop, and the
/// calls (their arguments and results passed through memory) cost 7-15% of a render.
#define RBPT_INLINE [[gnu::always_inline]] inline

namespace rbpt {

constexpr float Pi = 3.14159265358979323846f;
constexpr float InvPi = 0.31830988618379067154f;
constexpr float InvTwoPi = 0.15915494309189533577f;
constexpr float InvFourPi = 0.07957747154594766788f;
constexpr float Infinity = std::numeric_limits<float>::infinity();
/// Mitsuba's ray epsilon for float: 1500 ulps of 1 (math::RayEpsilon).
constexpr float RayEpsilon = 1500.f * 5.9604644775390625e-8f;
/// Shadow rays stop this fraction of their length short of the point they aim at.
constexpr float ShadowEpsilon = 10.f * RayEpsilon;
/// Half an ulp of 1 in float: the relative rounding error of one operation.
constexpr float MachineEpsilon = 5.9604644775390625e-8f;

/// Bound on the relative error of n chained float operations (Higham's gamma_n, as pbrt).
constexpr float gamma(int n) { return (float(n) * MachineEpsilon) / (1.f - float(n) * MachineEpsilon); }

/// The next float above / below v (for rounding ray origins away from a surface).
/// (std::nextafter, but inline: libm's is an out-of-line call on every spawned ray.)
inline float next_float_up(float v) {
    if (!(v < Infinity)) return v;  // +inf and NaN stay
    uint32_t bits;
    std::memcpy(&bits, &v, sizeof bits);
    if (v == 0.f) bits = 1u;  // +0 and -0 step to the smallest positive denormal
    else if (v > 0.f) ++bits;
    else --bits;
    std::memcpy(&v, &bits, sizeof v);
    return v;
}
inline float next_float_down(float v) { return -next_float_up(-v); }

struct Vec2 {
    float x = 0, y = 0;
};

/// e^x for float x, from a polynomial (within 2 ulps of libm's expf; x below -87 gives
/// e^-87): unlike libm's, it can be called in a loop that the compiler vectorises.
RBPT_INLINE float exp_poly(float x) {
    x = std::max(x, -87.f);
    // x = n ln2 + r, |r| <= ln2 / 2 (n rounded by the 1.5 * 2^23 trick; ln2 in two parts)
    float n = (x * 1.44269504f + 12582912.f) - 12582912.f;
    float r = (x - n * 0.693145751953125f) - n * 1.428606765330187e-6f;
    // e^r to degree 7 (relative error below 1e-8), times 2^n from its exponent bits
    float p = 1.f / 5040.f;
    p = p * r + 1.f / 720.f;
    p = p * r + 1.f / 120.f;
    p = p * r + 1.f / 24.f;
    p = p * r + 1.f / 6.f;
    p = p * r + 0.5f;
    p = p * r + 1.f;
    p = p * r + 1.f;
    int32_t bits = (int32_t(n) + 127) << 23;
    float scale;
    std::memcpy(&scale, &bits, sizeof scale);
    return p * scale;
}

/// atan(y / x) in the quadrant of (x, y), as std::atan2 (to 2e-7 rad; atan2(0, 0) is 0),
/// without libm, so that vectorised loops can call it: Cephes' atanf (its argument reduced
/// to [0, tan(pi/8)] by the identities at pi/4 and pi/2, then a polynomial of degree 9).
RBPT_INLINE float atan2_poly(float y, float x) {
    float ax = std::abs(x), ay = std::abs(y);
    float a = std::max(ax, ay), b = std::min(ax, ay);
    float t = a > 0.f ? b / a : 0.f;  // in [0, 1]: atan(t), then pi/2 - it where |y| > |x|
    float above = t > 0.41421356f ? 1.f : 0.f;
    float base = above != 0.f ? 0.78539816f : 0.f;
    t = above != 0.f ? (t - 1.f) / (t + 1.f) : t;
    float z = t * t;
    float p = 8.05374449538e-2f;
    p = p * z - 1.38776856032e-1f;
    p = p * z + 1.99777106478e-1f;
    p = p * z - 3.33329491539e-1f;
    float r = base + ((p * z) * t + t);
    r = ay > ax ? 1.57079633f - r : r;
    r = x < 0.f ? 3.14159265f - r : r;
    return std::copysign(r, y);
}

/// acos(x) for x in [0, 1] (Abramowitz and Stegun 4.4.46: absolute error below 2e-8).
RBPT_INLINE float acos_poly(float x) {
    float p = -0.0012624911f;
    p = p * x + 0.0066700901f;
    p = p * x - 0.0170881256f;
    p = p * x + 0.0308918810f;
    p = p * x - 0.0501743046f;
    p = p * x + 0.0889789874f;
    p = p * x - 0.2145988016f;
    p = p * x + 1.5707963050f;
    return std::sqrt(std::max(0.f, 1.f - x)) * p;
}

/// acos(x) for x in [-1, 1] (x clamped to it), from acos_poly (acos(-x) = pi - acos(x)).
RBPT_INLINE float acos_full(float x) {
    float r = acos_poly(std::min(std::abs(x), 1.f));
    return x < 0.f ? 3.14159265f - r : r;
}

/// log(x) for a normal, finite float x > 0, without libm, so that vectorised loops can call
/// it: x = m 2^e with m in [sqrt(1/2), sqrt(2)), and log(m) from Cephes' logf polynomial in
/// m - 1 (within 2 ulps of libm's, tests/cpp test13); ln2 in two parts.
RBPT_INLINE float log_poly(float x) {
    int32_t bits;
    std::memcpy(&bits, &x, sizeof bits);
    float e = float(((bits >> 23) & 0xff) - 127);
    int32_t mantissa = (bits & 0x007fffff) | 0x3f800000;  // m in [1, 2)
    float m;
    std::memcpy(&m, &mantissa, sizeof m);
    float high = m > 1.41421356f ? 1.f : 0.f;
    m = high != 0.f ? 0.5f * m : m;
    e = e + high;
    float f = m - 1.f, z = f * f;
    float p = 7.0376836292e-2f;
    p = p * f - 1.1514610310e-1f;
    p = p * f + 1.1676998740e-1f;
    p = p * f - 1.2420140846e-1f;
    p = p * f + 1.4249322787e-1f;
    p = p * f - 1.6668057665e-1f;
    p = p * f + 2.0000714765e-1f;
    p = p * f - 2.4999993993e-1f;
    p = p * f + 3.3333331174e-1f;
    float y = (p * f) * z;
    y = y + -2.12194440e-4f * e;
    y = y - 0.5f * z;
    return (f + y) + 0.693359375f * e;
}

struct Vec3 {
    float x = 0, y = 0, z = 0;
    Vec3() = default;
    constexpr Vec3(float x, float y, float z) : x(x), y(y), z(z) {}
    float operator[](int i) const { return i == 0 ? x : (i == 1 ? y : z); }
    float &operator[](int i) { return i == 0 ? x : (i == 1 ? y : z); }
    Vec3 operator-() const { return {-x, -y, -z}; }
    Vec3 &operator+=(const Vec3 &b) { x += b.x; y += b.y; z += b.z; return *this; }
};

inline Vec3 operator+(const Vec3 &a, const Vec3 &b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline Vec3 operator-(const Vec3 &a, const Vec3 &b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline Vec3 operator*(const Vec3 &a, const Vec3 &b) { return {a.x * b.x, a.y * b.y, a.z * b.z}; }
inline Vec3 operator*(const Vec3 &a, float s) { return {a.x * s, a.y * s, a.z * s}; }
inline Vec3 operator*(float s, const Vec3 &a) { return a * s; }
inline Vec3 operator/(const Vec3 &a, float s) { return a * (1.f / s); }
inline float dot(const Vec3 &a, const Vec3 &b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline Vec3 cross(const Vec3 &a, const Vec3 &b) {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline float squared_norm(const Vec3 &a) { return dot(a, a); }
RBPT_INLINE float norm(const Vec3 &a) { return std::sqrt(dot(a, a)); }
// (Forced inline: the SIMD loops of wavefront.cpp that call them vectorise only if inlined.)
RBPT_INLINE Vec3 normalize(const Vec3 &a) { return a / norm(a); }
inline Vec3 vmin(const Vec3 &a, const Vec3 &b) {
    return {std::min(a.x, b.x), std::min(a.y, b.y), std::min(a.z, b.z)};
}
inline Vec3 vmax(const Vec3 &a, const Vec3 &b) {
    return {std::max(a.x, b.x), std::max(a.y, b.y), std::max(a.z, b.z)};
}
inline Vec3 vabs(const Vec3 &a) { return {std::abs(a.x), std::abs(a.y), std::abs(a.z)}; }
inline float max_abs_component(const Vec3 &a) {
    return std::max(std::abs(a.x), std::max(std::abs(a.y), std::abs(a.z)));
}
inline Vec3 reflect(const Vec3 &wi, const Vec3 &m) { return 2.f * dot(wi, m) * m - wi; }
inline float safe_sqrt(float x) { return std::sqrt(std::max(x, 0.f)); }

/// Orthonormal basis around a unit normal n (Duff et al. 2017, branchless).
struct Frame {
    Vec3 s, t, n;
    Frame() = default;
    explicit Frame(const Vec3 &n_) : n(n_) {
        float sign = std::copysign(1.f, n.z);
        float a = -1.f / (sign + n.z), b = n.x * n.y * a;
        s = {1.f + sign * n.x * n.x * a, sign * b, -sign * n.x};
        t = {b, sign + n.y * n.y * a, -n.y};
    }
    Vec3 to_local(const Vec3 &v) const { return {dot(v, s), dot(v, t), dot(v, n)}; }
    Vec3 to_world(const Vec3 &v) const { return s * v.x + t * v.y + n * v.z; }
};

struct Ray {
    Vec3 o, d;
    float tmin = 0.f, tmax = Infinity;
};

/// An RGB triple of number type T; the spectrum type of the float and double renderers.
template <typename T>
struct RGB {
    T v[3];
    RGB() : v{T(0), T(0), T(0)} {}
    RGB(T s) : v{s, s, s} {}  // NOLINT: broadcasting a scalar is intended
    RGB(T r, T g, T b) : v{r, g, b} {}
    const T &operator[](int i) const { return v[i]; }
    T &operator[](int i) { return v[i]; }
    RGB &operator+=(const RGB &b) { for (int i = 0; i < 3; ++i) v[i] += b.v[i]; return *this; }
    RGB &operator*=(const RGB &b) { for (int i = 0; i < 3; ++i) v[i] *= b.v[i]; return *this; }
};

#define RBPT_RGB_BINOP(op)                                                              \
    template <typename T>                                                               \
    inline RGB<T> operator op(const RGB<T> &a, const RGB<T> &b) {                       \
        return {a.v[0] op b.v[0], a.v[1] op b.v[1], a.v[2] op b.v[2]};                  \
    }                                                                                   \
    template <typename T>                                                               \
    inline RGB<T> operator op(const RGB<T> &a, T s) {                                   \
        return {a.v[0] op s, a.v[1] op s, a.v[2] op s};                                 \
    }                                                                                   \
    template <typename T>                                                               \
    inline RGB<T> operator op(T s, const RGB<T> &a) {                                   \
        return {s op a.v[0], s op a.v[1], s op a.v[2]};                                 \
    }
RBPT_RGB_BINOP(+)
RBPT_RGB_BINOP(-)
RBPT_RGB_BINOP(*)
RBPT_RGB_BINOP(/)
#undef RBPT_RGB_BINOP

/// Plain float colour for detached quantities (sampling decisions, Russian roulette).
using Color3f = RGB<float>;

/// Number-type traits: Real is the scalar type that parameters such as roughness take, and
/// detach() drops any derivative information. Specialised by the autodiff types.
template <typename S>
struct SpectrumTraits;

template <typename T>
struct SpectrumTraits<RGB<T>> {
    using Real = T;
    static Color3f detach(const RGB<T> &s) {
        return {float(s.v[0]), float(s.v[1]), float(s.v[2])};
    }
    static bool is_finite(const RGB<T> &s) {
        return std::isfinite(s.v[0]) && std::isfinite(s.v[1]) && std::isfinite(s.v[2]);
    }
    /// Whether the value carries a derivative (never, for plain numbers).
    static bool has_derivative(const RGB<T> &) { return false; }
};

template <typename S>
using real_t = typename SpectrumTraits<S>::Real;

template <typename S>
inline Color3f detach(const S &s) { return SpectrumTraits<S>::detach(s); }

/// Value of a scalar of any number type, without derivatives (overloaded by autodiff types).
inline float detach_real(float x) { return x; }
inline float detach_real(double x) { return float(x); }
/// The same value as a constant of its own type (overloaded by autodiff types).
inline float no_grad(float x) { return x; }
inline double no_grad(double x) { return x; }

inline float max_component(const Color3f &c) { return std::max(c.v[0], std::max(c.v[1], c.v[2])); }
inline float mean(const Color3f &c) { return (c.v[0] + c.v[1] + c.v[2]) / 3.f; }

}  // namespace rbpt
