// Tests of csrc/autodiff.h (reverse mode, Var) and csrc/dual.h (forward mode, Dual): values and
// derivatives of every operation against analytic derivatives and central finite differences,
// the tape's bookkeeping (constants, accumulation, custom nodes, reuse without allocation, long
// chains) and the unbiased integrate() operator, including its independence from the forward
// samples and nested use; the vectorisable math of math.h and microfacet.h, and a bitmap's
// wrapped texel pairs (textures.h). Prints "N passed, M failed" last; exits nonzero on any failure.
//
// Build: g++ -std=c++17 -O2 -Wall -I csrc tests/cpp/test_autodiff.cpp (tests/test_autodiff.py).

#include <array>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <new>
#include <type_traits>
#include <utility>
#include <vector>

#include "autodiff.h"
#include "dual.h"
#include "microfacet.h"
#include "sampler.h"
#include "textures.h"

// ---- Heap allocation counter (to show that recording allocates nothing after warm-up) ------

static size_t g_allocations = 0;

void *operator new(std::size_t n) {
    ++g_allocations;
    if (void *p = std::malloc(n ? n : 1)) return p;
    throw std::bad_alloc();
}
// Not inlined, so that GCC does not pair the inlined free() with operator new and warn.
__attribute__((noinline)) void operator delete(void *p) noexcept { std::free(p); }
__attribute__((noinline)) void operator delete(void *p, std::size_t) noexcept { std::free(p); }

// ---- A tiny check framework ------------------------------------------------------------------

using namespace rbpt;

static int g_passed = 0, g_failed = 0;
static const char *g_test = "";

static void check(bool ok, const char *what, int line) {
    if (ok) {
        ++g_passed;
    } else {
        ++g_failed;
        std::printf("FAIL [%s] line %d: %s\n", g_test, line, what);
    }
}

/// |a - b| <= tol max(1, |b|), reporting both values on failure.
static void check_close(double a, double b, double tol, const char *what, int line) {
    bool ok = std::abs(a - b) <= tol * std::max(1.0, std::abs(b));
    check(ok, what, line);
    if (!ok) std::printf("    got %.17g, expected %.17g (tol %g)\n", a, b, tol);
}

template <typename A, typename B>
static void check_rgb_close(const RGB<A> &a, const RGB<B> &b, double tol, const char *what,
                            int line) {
    for (int i = 0; i < 3; ++i) check_close(double(a[i]), double(b[i]), tol, what, line);
}

#define CHECK(cond) check(bool(cond), #cond, __LINE__)
#define CHECK_CLOSE(a, b, tol) check_close(double(a), double(b), tol, #a " ~ " #b, __LINE__)
#define CHECK_RGB(a, b, tol) check_rgb_close(a, b, tol, #a " ~ " #b, __LINE__)

template <typename T>
constexpr double tolerance() {
    return std::is_same_v<T, float> ? 2e-6 : 1e-13;
}

template <typename N>
constexpr bool is_var_v = false;
template <typename T>
constexpr bool is_var_v<Var<T>> = true;

template <typename T>
static RGB<T> rgb(double r, double g, double b) {
    return {T(r), T(g), T(b)};
}

template <typename T>
static RGB<double> to_double(const RGB<T> &a) {
    return {double(a[0]), double(a[1]), double(a[2])};
}

template <typename T>
static size_t tape_size() {
    return Tape<T>::local().size();
}

// ---- Differentiation drivers: the same generic function through Var or Dual ----------------

/// Value and derivative (per channel) of y = f(x) at x0.
template <typename N, typename F>
static std::array<RGB<typename N::Scalar>, 2> diff1(F f, const RGB<typename N::Scalar> &x0) {
    using T = typename N::Scalar;
    if constexpr (is_var_v<N>) {
        tape_reset<T>();
        Var<T> x(x0, true);
        Var<T> y = f(x);
        y.backward();
        return {y.value(), x.grad()};
    } else {
        Dual<T> y = f(Dual<T>(x0, RGB<T>(T(1))));
        return {y.v, y.d};
    }
}

/// Value and partial derivatives (per channel) of z = f(x, y) at (x0, y0).
template <typename N, typename F>
static std::array<RGB<typename N::Scalar>, 3> diff2(F f, const RGB<typename N::Scalar> &x0,
                                                    const RGB<typename N::Scalar> &y0) {
    using T = typename N::Scalar;
    if constexpr (is_var_v<N>) {
        tape_reset<T>();
        Var<T> x(x0, true), y(y0, true);
        Var<T> z = f(x, y);
        z.backward();
        return {z.value(), x.grad(), y.grad()};
    } else {
        Dual<T> zx = f(Dual<T>(x0, RGB<T>(T(1))), Dual<T>(y0));
        Dual<T> zy = f(Dual<T>(x0), Dual<T>(y0, RGB<T>(T(1))));
        return {zx.v, zx.d, zy.d};
    }
}

/// Central finite difference (per channel) of a componentwise f, evaluated in double.
template <typename F>
static RGB<double> central_difference(F f, const RGB<double> &x0, double h = 1e-6) {
    Var<double> p = f(Var<double>(x0 + h)), m = f(Var<double>(x0 - h));
    return (p.value() - m.value()) / (2.0 * h);
}

// ---- 1. Every operation and function against its analytic derivative ----------------------

/// Compare f (on N) with the scalar reference fd (value) and dfd (derivative) per channel.
template <typename N, typename F, typename Ref, typename DRef>
static void check_unary(const char *name, F f, Ref ref, DRef dref, RGB<double> x0d) {
    using T = typename N::Scalar;
    g_test = name;
    RGB<T> x0 = rgb<T>(x0d[0], x0d[1], x0d[2]);
    auto [value, grad] = diff1<N>(f, x0);
    for (int i = 0; i < 3; ++i) {
        double xi = double(x0[i]);  // the input as rounded to T
        CHECK_CLOSE(value[i], ref(xi), tolerance<T>());
        CHECK_CLOSE(grad[i], dref(xi), tolerance<T>());
    }
}

template <typename N, typename F, typename Ref, typename DX, typename DY>
static void check_binary(const char *name, F f, Ref ref, DX dx, DY dy, RGB<double> x0d,
                         RGB<double> y0d) {
    using T = typename N::Scalar;
    g_test = name;
    RGB<T> x0 = rgb<T>(x0d[0], x0d[1], x0d[2]), y0 = rgb<T>(y0d[0], y0d[1], y0d[2]);
    auto [value, gx, gy] = diff2<N>(f, x0, y0);
    for (int i = 0; i < 3; ++i) {
        double xi = double(x0[i]), yi = double(y0[i]);
        CHECK_CLOSE(value[i], ref(xi, yi), tolerance<T>());
        CHECK_CLOSE(gx[i], dx(xi, yi), tolerance<T>());
        CHECK_CLOSE(gy[i], dy(xi, yi), tolerance<T>());
    }
}

template <typename N>
static void test01_operations() {
    const RGB<double> x0{0.3, 0.7, 1.9}, xs{-0.4, 0.7, 1.3};
    auto one = [](double) { return 1.0; };
    check_unary<N>("negate", [](auto x) { return -x; }, [](double x) { return -x; },
                   [](double) { return -1.0; }, x0);
    check_unary<N>("exp", [](auto x) { return exp(x); }, [](double x) { return std::exp(x); },
                   [](double x) { return std::exp(x); }, x0);
    check_unary<N>("log", [](auto x) { return log(x); }, [](double x) { return std::log(x); },
                   [](double x) { return 1.0 / x; }, x0);
    check_unary<N>("sqrt", [](auto x) { return sqrt(x); },
                   [](double x) { return std::sqrt(x); },
                   [](double x) { return 0.5 / std::sqrt(x); }, x0);
    check_unary<N>("erf", [](auto x) { return erf(x); }, [](double x) { return std::erf(x); },
                   [](double x) { return 2.0 / std::sqrt(M_PI) * std::exp(-x * x); }, xs);
    check_unary<N>("pow", [](auto x) { return pow(x, 2.5f); },
                   [](double x) { return std::pow(x, 2.5); },
                   [](double x) { return 2.5 * std::pow(x, 1.5); }, x0);
    check_unary<N>("abs", [](auto x) { return abs(x); }, [](double x) { return std::abs(x); },
                   [](double x) { return x > 0 ? 1.0 : -1.0; }, xs);
    check_unary<N>("x * 0.5f", [](auto x) { return x * 0.5f; }, [](double x) { return x * 0.5; },
                   [](double) { return 0.5; }, x0);
    check_unary<N>("1.f - x", [](auto x) { return 1.f - x; }, [](double x) { return 1.0 - x; },
                   [](double) { return -1.0; }, x0);
    check_unary<N>("2.f / x", [](auto x) { return 2.f / x; }, [](double x) { return 2.0 / x; },
                   [](double x) { return -2.0 / (x * x); }, x0);
    check_unary<N>("x + 3", [](auto x) { return x + 3; }, [](double x) { return x + 3.0; }, one,
                   x0);
    check_unary<N>("x - 1.5", [](auto x) { return x - 1.5; }, [](double x) { return x - 1.5; },
                   one, x0);
    check_unary<N>("x / 4.f", [](auto x) { return x / 4.f; }, [](double x) { return x / 4.0; },
                   [](double) { return 0.25; }, x0);
    check_unary<N>("min(x, 1)", [](auto x) { return min(x, 1.f); },
                   [](double x) { return std::min(x, 1.0); },
                   [](double x) { return x <= 1.0 ? 1.0 : 0.0; }, x0);
    check_unary<N>("max(0.5, x)", [](auto x) { return max(0.5, x); },
                   [](double x) { return std::max(0.5, x); },
                   [](double x) { return x >= 0.5 ? 1.0 : 0.0; }, x0);
    check_unary<N>("x.detach() * x", [](auto x) { return x.detach() * x; },
                   [](double x) { return x * x; }, [](double x) { return x; }, x0);
    check_unary<N>("no_grad(x) + x", [](auto x) { return no_grad(x) + x; },
                   [](double x) { return 2 * x; }, one, x0);

    const RGB<double> a0{0.3, 1.7, -0.8}, b0{1.1, 0.4, 2.5};
    auto zero = [](double, double) { return 0.0; };
    auto plus1 = [](double, double) { return 1.0; };
    check_binary<N>("x + y", [](auto x, auto y) { return x + y; },
                    [](double x, double y) { return x + y; }, plus1, plus1, a0, b0);
    check_binary<N>("x - y", [](auto x, auto y) { return x - y; },
                    [](double x, double y) { return x - y; }, plus1,
                    [](double, double) { return -1.0; }, a0, b0);
    check_binary<N>("x * y", [](auto x, auto y) { return x * y; },
                    [](double x, double y) { return x * y; },
                    [](double, double y) { return y; }, [](double x, double) { return x; }, a0,
                    b0);
    check_binary<N>("x / y", [](auto x, auto y) { return x / y; },
                    [](double x, double y) { return x / y; },
                    [](double, double y) { return 1.0 / y; },
                    [](double x, double y) { return -x / (y * y); }, a0, b0);
    check_binary<N>("min(x, y)", [](auto x, auto y) { return min(x, y); },
                    [](double x, double y) { return std::min(x, y); },
                    [](double x, double y) { return x <= y ? 1.0 : 0.0; },
                    [](double x, double y) { return x <= y ? 0.0 : 1.0; }, a0, b0);
    check_binary<N>("max(x, y)", [](auto x, auto y) { return max(x, y); },
                    [](double x, double y) { return std::max(x, y); },
                    [](double x, double y) { return x >= y ? 1.0 : 0.0; },
                    [](double x, double y) { return x >= y ? 0.0 : 1.0; }, a0, b0);
    check_binary<N>("x += y", [](auto x, auto y) { x += y; return x; },
                    [](double x, double y) { return x + y; }, plus1, plus1, a0, b0);
    check_binary<N>("x -= y", [](auto x, auto y) { x -= y; return x; },
                    [](double x, double y) { return x - y; }, plus1,
                    [](double, double) { return -1.0; }, a0, b0);
    check_binary<N>("x *= y", [](auto x, auto y) { x *= y; return x; },
                    [](double x, double y) { return x * y; },
                    [](double, double y) { return y; }, [](double x, double) { return x; }, a0,
                    b0);
    check_binary<N>("x /= y", [](auto x, auto y) { x /= y; return x; },
                    [](double x, double y) { return x / y; },
                    [](double, double y) { return 1.0 / y; },
                    [](double x, double y) { return -x / (y * y); }, a0, b0);
    check_binary<N>("x - x (same operand)", [](auto x, auto) { return x - x; }, zero, zero,
                    zero, a0, b0);
    check_binary<N>("rgb * x", [](auto x, auto) {
                        using T = typename decltype(x)::Scalar;
                        return RGB<T>(T(2), T(2), T(2)) * x;
                    },
                    [](double x, double) { return 2 * x; },
                    [](double, double) { return 2.0; }, zero, a0, b0);
}

// ---- 2. Composite expressions against finite differences; Var and Dual agree --------------

/// The generic idioms the path tracer uses, as composite functions of one scalar.
struct Composites {
    /// GGX Smith G1 as written in microfacet.h.
    static constexpr auto ggx_g1 = [](auto alpha) {
        using N = decltype(alpha);
        N tan2 = 0.8f;
        return 2.f / (1.f + sqrt(1.f + alpha * alpha * tan2));
    };
    /// Beckmann D: exp(-t / a^2) / (pi a^2 c).
    static constexpr auto beckmann = [](auto a) {
        return exp(-0.3f / (a * a)) / (Pi * a * a * 0.8f);
    };
    /// Beckmann Smith G1, with erf.
    static constexpr auto beckmann_g1 = [](auto alpha) {
        auto a = 1.f / (alpha * 1.3f);
        auto lambda = (erf(a) - 1.f) * 0.5f + exp(-a * a) / (a * (2.f * 1.7724538509055159f));
        return 1.f / (1.f + lambda);
    };
    /// A diamond: x reaches the result along several paths.
    static constexpr auto diamond = [](auto x) {
        auto y = 2.f * x;
        return (x * y + exp(-x) / y) * log(1.f + x * x);
    };
    static constexpr auto mixed = [](auto x) {
        using N = decltype(x);
        using R = real_t<N>;
        N s(0.f);
        s += pow(abs(x - 2.f), 1.5f) * sqrt(x);
        s -= min(x, x * x);
        s *= R(1.f / 0.7f);
        return s + max(x * 0.5f, 1.f - x);
    };
};

template <typename N, typename F>
static void check_composite(const char *name, F f, RGB<double> x0d) {
    using T = typename N::Scalar;
    g_test = name;
    RGB<T> x0 = rgb<T>(x0d[0], x0d[1], x0d[2]);
    auto [value, grad] = diff1<N>(f, x0);
    RGB<double> x0r = to_double(x0);
    Var<double> reference = f(Var<double>(x0r));
    // Float values carry float rounding; central differences in double are good to ~1e-8.
    double tol = std::is_same_v<T, float> ? 2e-5 : 1e-7;
    CHECK_RGB(value, reference.value(), (std::is_same_v<T, float> ? 2e-6 : 1e-14));
    CHECK_RGB(grad, central_difference(f, x0r), tol);
}

template <typename N>
static void test02_composites() {
    const RGB<double> alphas{0.1, 0.3, 0.7}, xs{0.4, 0.9, 1.6};
    check_composite<N>("ggx_g1", Composites::ggx_g1, alphas);
    check_composite<N>("beckmann", Composites::beckmann, alphas);
    check_composite<N>("beckmann_g1", Composites::beckmann_g1, alphas);
    check_composite<N>("diamond", Composites::diamond, xs);
    check_composite<N>("mixed", Composites::mixed, xs);
}

/// Reverse and forward mode give the same derivative of the same expression.
static void test03_var_matches_dual() {
    g_test = "var_matches_dual";
    const RGB<double> a0{0.05, 0.3, 0.9};
    auto check_same = [&](auto f) {
        auto [vv, gv] = diff1<Var<double>>(f, a0);
        auto [vd, gd] = diff1<Dual<double>>(f, a0);
        CHECK_RGB(vv, vd, 1e-15);
        CHECK_RGB(gv, gd, 1e-13);
    };
    check_same(Composites::beckmann);
    check_same(Composites::beckmann_g1);
    check_same(Composites::ggx_g1);
    check_same(Composites::diamond);
    check_same(Composites::mixed);
}

/// microfacet.h's D, G1 and visible-normal pdf instantiated with Var and Dual roughness.
template <typename N>
static void test04_microfacet() {
    using T = typename N::Scalar;
    g_test = is_var_v<N> ? "microfacet (Var)" : "microfacet (Dual)";
    Vec3 wi = normalize(Vec3(0.3f, -0.2f, 0.8f)), wo = normalize(Vec3(-0.4f, 0.1f, 0.7f));
    Vec3 h = normalize(wi + wo);
    double tol = std::is_same_v<T, float> ? 1e-4 : 1e-7;
    for (MicrofacetType type : {MicrofacetType::Beckmann, MicrofacetType::GGX}) {
        for (double alpha : {0.15, 0.4, 0.8}) {
            auto d_of = [&](auto a) { return microfacet_D(type, a, h); };
            auto g_of = [&](auto a) { return smith_G1(type, a, wi, h); };
            auto p_of = [&](auto a) { return visible_normal_pdf(type, a, wo, h); };
            auto check_fn = [&](auto f) {
                auto [value, grad] = diff1<N>(f, RGB<T>(T(alpha)));
                double a = double(T(alpha)), eps = 1e-6;
                double fd = (f(a + eps) - f(a - eps)) / (2 * eps);
                CHECK_CLOSE(value[0], f(a), (std::is_same_v<T, float> ? 1e-5 : 1e-14));
                CHECK_CLOSE(grad[0], fd, tol * std::max(1.0, std::abs(f(a))));
                CHECK(value[0] == value[2] && grad[0] == grad[2]);  // scalars stay scalars
            };
            check_fn(d_of);
            check_fn(g_of);
            check_fn(p_of);
        }
    }
}

// ---- 3. The tape: constants, NoRecord, accumulation, diamonds, custom nodes ----------------

template <typename T>
static void test05_constants_record_nothing() {
    g_test = "constants_record_nothing";
    static_assert(std::is_same_v<real_t<Var<T>>, Var<T>>);
    static_assert(std::is_same_v<real_t<Dual<T>>, Dual<T>>);
    static_assert(std::is_trivially_copyable_v<Var<T>>);
    tape_reset<T>();
    size_t n0 = tape_size<T>();
    Var<T> c(rgb<T>(4, 5, 6));
    Var<T> d = {7, 8, 9};
    Var<T> k = c + d;
    Var<T> e = exp(c / d) * sqrt(d) - log(c) + pow(c, T(2)) * 0.5f + 1.f;
    CHECK(tape_size<T>() == n0);
    CHECK(!k.requires_grad() && !e.requires_grad());
    CHECK_RGB(k.value(), rgb<T>(11, 13, 15), 0);
    // The idioms of generic code: S(0.f), real_t<S>(1.f / q), scalar broadcast.
    Var<T> zero(0.f), q = real_t<Var<T>>(1.f / 0.25f);
    CHECK(tape_size<T>() == n0);
    CHECK_RGB(zero.value(), RGB<T>(T(0)), 0);
    CHECK_RGB(q.value(), RGB<T>(T(4)), 0);

    // Mixing: only what involves the variable is recorded, one node per operation.
    Var<T> x(rgb<T>(1, 2, 3), true);
    size_t n1 = tape_size<T>();
    CHECK(n1 == n0 + 1);
    Var<T> y = x * c + c * d;  // x * c and + are recorded, c * d is not
    CHECK(tape_size<T>() == n1 + 2);
    Var<T> z = exp(x) + 0.5f;
    CHECK(tape_size<T>() == n1 + 4);
    CHECK(y.requires_grad() && z.requires_grad());
    y.backward();
    CHECK_RGB(x.grad(), c.value(), 0);

    // Backward on a constant is a no-op; a constant's gradient is zero.
    c.backward();
    k.backward(rgb<T>(1, 2, 3));
    CHECK_RGB(x.grad(), c.value(), 0);
    CHECK_RGB(c.grad(), RGB<T>(), 0);
    CHECK(y.grad()[0] == T(0));  // non-leaf: no stored gradient

    // NoRecord turns recorded operations and custom nodes into constants.
    size_t n2 = tape_size<T>();
    {
        NoRecord guard;
        Var<T> w = x * x + exp(x);
        Var<T> custom(w, [](const RGB<T> &) {});
        CHECK(!w.requires_grad() && !custom.requires_grad());
        CHECK_RGB(w.value(), x.value() * x.value() + rgb<T>(std::exp(1.0), std::exp(2.0),
                                                             std::exp(3.0)),
                  tolerance<T>());
        CHECK(tape_size<T>() == n2);
    }
    Var<T> after = x * x;
    CHECK(after.requires_grad() && tape_size<T>() == n2 + 1);

    // Traits and detaching.
    Color3f dc = detach(x);
    CHECK(dc[0] == 1.f && dc[1] == 2.f && dc[2] == 3.f);
    CHECK(detach_real(x) == 1.f);
    CHECK(SpectrumTraits<Var<T>>::is_finite(x));
    CHECK(!SpectrumTraits<Var<T>>::is_finite(x / 0.f));
    CHECK(!x.detach().requires_grad() && x.detach().value()[2] == T(3));
    Dual<T> dd(rgb<T>(2, 3, 4), RGB<T>(T(1)));
    CHECK(detach_real(dd) == 2.f && detach(dd)[2] == 4.f && dd.detach().d[0] == T(0));
    CHECK(!SpectrumTraits<Dual<T>>::is_finite(dd / 0.f));
}

template <typename T>
static void test06_accumulation_and_diamond() {
    g_test = "accumulation_and_diamond";
    tape_reset<T>();
    Var<T> x(rgb<T>(0.5, 1.5, -2), true);
    Var<T> y = x * x;
    y.backward();
    CHECK_RGB(x.grad(), T(2) * x.value(), 0);
    y.backward(RGB<T>(T(0.5)));  // accumulates like torch
    CHECK_RGB(x.grad(), T(3) * x.value(), tolerance<T>());
    y.backward(rgb<T>(1, 0, 2));  // a per-channel seed
    CHECK_RGB(x.grad(), (T(3) + T(2) * rgb<T>(1, 0, 2)) * x.value(), tolerance<T>());
    x.zero_grad();
    CHECK_RGB(x.grad(), RGB<T>(), 0);
    y.backward();
    CHECK_RGB(x.grad(), T(2) * x.value(), 0);

    // A diamond: y = x^2 + x used twice in z = y * y; dz/dx = 2 y (2 x + 1).
    x.zero_grad();
    Var<T> u = x * x + x;
    Var<T> z = u * u;
    z.backward();
    CHECK_RGB(x.grad(), T(2) * u.value() * (T(2) * x.value() + T(1)), tolerance<T>());

    // Two variables, one shared subexpression: f = (x y) / (x + y) + x y.
    x.zero_grad();
    Var<T> w(rgb<T>(0.3, 2, 5), true);
    Var<T> p = x * w;
    Var<T> f = p / (x + w) + p;
    f.backward();
    for (int i = 0; i < 3; ++i) {
        double a = double(x.value()[i]), b = double(w.value()[i]);
        CHECK_CLOSE(x.grad()[i], b * b / ((a + b) * (a + b)) + b, 10 * tolerance<T>());
        CHECK_CLOSE(w.grad()[i], a * a / ((a + b) * (a + b)) + a, 10 * tolerance<T>());
    }
}

/// A functor capturing what a bilinear parameter read needs (96 bytes in double).
template <typename T>
struct TexelRead {
    T *grad;              ///< the parameter's gradient buffer (H, W, 3)
    int64_t index[4];     ///< texel indices
    double weight[4];     ///< bilinear weights
    double check[3];      ///< padding the capture to ~96 bytes, and a canary
    void operator()(const RGB<T> &g) const {
        for (int k = 0; k < 4; ++k)
            for (int c = 0; c < 3; ++c) grad[3 * index[k] + c] += T(weight[k]) * g[c];
    }
};

static int g_live_destructions = 0;

/// Counts destructions of objects that were not moved from.
struct Counted {
    bool live = true;
    Counted() = default;
    Counted(Counted &&o) noexcept { o.live = false; }
    Counted(const Counted &) = default;
    ~Counted() {
        if (live) ++g_live_destructions;
    }
};

struct alignas(64) Aligned {
    double data[8];
};

template <typename T>
static void test07_custom_functors() {
    g_test = "custom_functors";
    tape_reset<T>();
    Var<T> x(rgb<T>(1, 2, 3), true);
    Var<T> y = x * 2.f;

    // The functor sees the gradient reaching its node, and replaces y's derivative.
    RGB<T> seen(T(-1));
    int calls = 0;
    Var<T> z(y, [&seen, &calls](const RGB<T> &g) {
        seen = g;
        ++calls;
    });
    CHECK(z.requires_grad());
    CHECK_RGB(z.value(), y.value(), 0);
    Var<T> loss = z * rgb<T>(3, 4, 5) + 1.f;
    loss.backward();
    CHECK(calls == 1);
    CHECK_RGB(seen, rgb<T>(3, 4, 5), 0);
    CHECK_RGB(x.grad(), RGB<T>(), 0);  // y's graph is not followed

    // ... unless the functor chains into it (a deposit for the running sweep).
    Var<T> chained(y, [y](const RGB<T> &g) { y.backward(g * T(10)); });
    (chained * 3.f).backward();
    CHECK_RGB(x.grad(), RGB<T>(T(60)), 0);

    // A parameter read: a bilinear lookup depositing into a flat gradient buffer.
    x.zero_grad();
    std::vector<T> texels(4 * 4 * 3), grads(texels.size(), T(0));
    for (size_t i = 0; i < texels.size(); ++i) texels[i] = T(0.01 * double(i));
    TexelRead<T> read{grads.data(), {0, 1, 4, 5}, {0.1, 0.2, 0.3, 0.4}, {1.5, 2.5, 3.5}};
    static_assert(sizeof(TexelRead<T>) >= 88);
    RGB<T> value;
    for (int k = 0; k < 4; ++k)
        for (int c = 0; c < 3; ++c) value[c] += T(read.weight[k]) * texels[3 * read.index[k] + c];
    Var<T> texture(value, read);
    Var<T> shade = texture * texture * x;  // d/d texture = 2 texture x
    shade.backward();
    RGB<T> d_texture = T(2) * value * x.value();
    for (int k = 0; k < 4; ++k)
        for (int c = 0; c < 3; ++c)
            CHECK_CLOSE(grads[3 * read.index[k] + c], read.weight[k] * double(d_texture[c]),
                        tolerance<T>());
    CHECK_RGB(x.grad(), value * value, 0);

    // Captured data survives in the arena; over-aligned captures are aligned.
    bool intact = false, aligned = false;
    Aligned block;
    for (int i = 0; i < 8; ++i) block.data[i] = i * 1.25;
    std::array<double, 12> payload;
    for (int i = 0; i < 12; ++i) payload[i] = 3.0 * i + 0.5;
    Var<T> big(x, [payload, block, &intact, &aligned](const RGB<T> &) {
        intact = true;
        for (int i = 0; i < 12; ++i) intact = intact && payload[i] == 3.0 * i + 0.5;
        for (int i = 0; i < 8; ++i) intact = intact && block.data[i] == i * 1.25;
        aligned = reinterpret_cast<uintptr_t>(&block) % 64 == 0;
    });
    Var<T> t = x;
    for (int i = 0; i < 100; ++i) t = t * 1.f;  // more nodes recorded after the functor
    big.backward();
    CHECK(intact);
    CHECK(aligned);

    // Non-trivially destructible functors are destroyed once, when the tape is rewound.
    g_live_destructions = 0;
    {
        Counted counted;
        Var<T> c(x, [counted](const RGB<T> &) { (void)counted; });
        (void)c;
    }
    CHECK(g_live_destructions == 1);  // the test's own copy; the tape's is alive
    tape_reset<T>();
    CHECK(g_live_destructions == 2);
    tape_reset<T>();
    CHECK(g_live_destructions == 2);
}

// ---- 4. Reuse without reallocation, long chains --------------------------------------------

/// A uniform sampler on [0, 1) with pdf 1, from rbpt::Sampler's PCG32 stream.
struct UniformSampler {
    Sampler rng;
    std::pair<float, float> operator()() { return {rng.next_1d(), 1.f}; }
};

template <typename T>
static void workload(std::vector<T> &grads, uint64_t seed) {
    double sink_grads[1] = {0.0};
    Var<T> x(rgb<T>(0.5, 0.6, 0.7), true);
    Var<T> y = x;
    for (int i = 0; i < 2000; ++i) y = y * 0.999f + x * 0.001f;
    for (int k = 0; k < 50; ++k) {
        Var<T> texel(y.value(), TexelRead<T>{grads.data(), {0, 1, 4, 5}, {.1, .2, .3, .4}, {}});
        y = y + texel * 0.01f;
        y = y + Var<T>(y.value(), sink_grads, 1) * 0.01f;  // a sink node
    }
    Var<T> I = integrate([x](float u) { return exp(x * u); }, UniformSampler{Sampler(seed, 0, 0)},
                         8);
    (y * I).backward();
}

template <typename T>
static void test08_reuse_without_allocation() {
    g_test = "reuse_without_allocation";
    std::vector<T> grads(48, T(0));
    Tape<T> &tape = Tape<T>::local();
    tape.reset();
    workload(grads, 0);  // warm-up
    tape.reset();
    size_t nodes = tape.node_capacity(), arena = tape.arena_capacity();
    size_t allocations = g_allocations;
    for (uint64_t run = 1; run <= 20; ++run) {
        workload(grads, run);
        tape.reset();
    }
    CHECK(tape.size() == 0);
    CHECK(tape.node_capacity() == nodes);
    CHECK(tape.arena_capacity() == arena);
    CHECK(g_allocations == allocations);
    if (g_allocations != allocations)
        std::printf("    %zu heap allocations after warm-up\n", g_allocations - allocations);
}

template <typename T>
static void test09_long_chains() {
    g_test = "long_chains";
    tape_reset<T>();
    // y_{n+1} = y_n / 2 + x: dy/dx = 2 - 2^-n, over 2e5 recorded operations.
    Var<T> x(rgb<T>(0.1, 0.2, 0.3), true);
    Var<T> y = x;
    for (int i = 0; i < 100000; ++i) y = y * 0.5f + x;
    CHECK(tape_size<T>() == 200001);
    y.backward();
    CHECK_RGB(x.grad(), RGB<T>(T(2)), tolerance<T>());

    // 1e5 custom nodes, each chaining into the previous one from its functor: no recursion.
    tape_reset<T>();
    Var<T> v(rgb<T>(1, 2, 3), true);
    Var<T> c = v;
    for (int i = 0; i < 100000; ++i) {
        Var<T> prev = c;
        c = Var<T>(prev, [prev](const RGB<T> &g) { prev.backward(g); });
    }
    c.backward(rgb<T>(1, 2, 3));
    CHECK_RGB(v.grad(), rgb<T>(1, 2, 3), 0);
    tape_reset<T>();
}

// ---- 5. integrate(): independent samples, unbiased gradients, nesting ----------------------

/// A deterministic sequence u_k = frac(0.5 + k phi) (pdf 1): its position k is its own state
/// (copies continue independently), and every draw is also counted in *count.
struct CountingSampler {
    int *count;
    int k = 0;
    std::pair<double, double> operator()() {
        ++*count;
        return {u(k++), 1.0};
    }
    static double u(int k) {
        double v = 0.5 + 0.6180339887498949 * k;
        return v - std::floor(v);
    }
};

struct Stats {
    double sum = 0, sum2 = 0;
    int n = 0;
    void add(double x) { sum += x, sum2 += x * x, ++n; }
    double mean() const { return sum / n; }
    double standard_error() const {
        double m = mean();
        return std::sqrt(std::max(sum2 / n - m * m, 0.0) / (n - 1));
    }
};

/// Check |mean - expected| < 4 standard errors (and that the error is not degenerate).
static void check_unbiased(const Stats &s, double expected, const char *what, int line) {
    double se = s.standard_error();
    bool ok = std::abs(s.mean() - expected) < 4 * se + 1e-12 * std::abs(expected);
    check(ok, what, line);
    if (!ok || se <= 0)
        std::printf("    mean %.8g, expected %.8g, standard error %.3g\n", s.mean(), expected, se);
}
#define CHECK_UNBIASED(stats, expected) check_unbiased(stats, expected, #stats, __LINE__)

static double I_exact(double t) { return (std::exp(t) - 1) / t; }
static double dI_exact(double t) { return (std::exp(t) * (t - 1) + 1) / (t * t); }

template <typename T>
static void test10_integrate_uses_new_samples() {
    g_test = "integrate_uses_new_samples";
    tape_reset<T>();
    Var<T> theta(rgb<T>(0.5, 1, 2), true);
    int count = 0;
    size_t n0 = tape_size<T>();
    const int n = 8;
    Var<T> I = integrate([theta](double u) { return exp(theta * u); }, CountingSampler{&count}, n);
    CHECK(count == n);
    CHECK(tape_size<T>() == n0 + 1);  // the forward samples left no record
    CHECK(I.requires_grad());
    // Value: the estimate over samples 0..n-1; gradient: over the next n samples, n..2n-1.
    auto mean_over = [&](int first, auto g) {
        RGB<double> s;
        for (int k = first; k < first + n; ++k) s += g(CountingSampler::u(k));
        return s / double(n);
    };
    RGB<double> th = to_double(theta.value());
    auto f = [&](double u) { return RGB<double>(std::exp(th[0] * u), std::exp(th[1] * u),
                                                std::exp(th[2] * u)); };
    auto df = [&](double u) { return RGB<double>(u) * f(u); };
    CHECK_RGB(I.value(), mean_over(0, f), 10 * tolerance<T>());
    I.backward();
    CHECK(count == 2 * n);
    CHECK_RGB(theta.grad(), mean_over(n, df), 10 * tolerance<T>());
    CHECK(tape_size<T>() == n0 + 1);  // the inner samples were discarded
    I.backward(RGB<T>(T(2)));  // a second backward draws yet new samples and accumulates
    CHECK(count == 3 * n);
    CHECK_RGB(theta.grad(), mean_over(n, df) + 2.0 * mean_over(2 * n, df), 10 * tolerance<T>());
    {
        NoRecord guard;  // backward records what it needs even under NoRecord
        I.backward();
    }
    CHECK(count == 4 * n);
    CHECK_RGB(theta.grad(), mean_over(n, df) + 2.0 * mean_over(2 * n, df) + mean_over(3 * n, df),
              10 * tolerance<T>());

    // The custom node inside a larger graph: loss = I theta + exp(theta). The outer sweep
    // must carry both the inner deposit and theta's other paths.
    theta.zero_grad();
    count = 0;
    Var<T> J = integrate([theta](double u) { return exp(theta * u); }, CountingSampler{&count}, n);
    Var<T> loss = J * theta + exp(theta);
    loss.backward();
    RGB<double> expected = to_double(J.value()) + th * mean_over(n, df) +
                           RGB<double>(std::exp(th[0]), std::exp(th[1]), std::exp(th[2]));
    CHECK_RGB(theta.grad(), expected, 10 * tolerance<T>());

    // Under NoRecord, integrate gives a constant estimate.
    {
        NoRecord guard;
        count = 0;
        Var<T> K = integrate([theta](double u) { return exp(theta * u); },
                             CountingSampler{&count}, n);
        CHECK(!K.requires_grad() && count == n);
    }
    tape_reset<T>();
}

template <typename T>
static void test11_integrate_is_unbiased() {
    g_test = "integrate_is_unbiased";
    const double th[3] = {0.5, 1.0, 2.0};
    const int runs = 4000;
    Stats value[3], grad[3], grad_sq[3], naive_sq[3];
    for (int s = 0; s < runs; ++s) {
        tape_reset<T>();
        Var<T> theta(rgb<T>(th[0], th[1], th[2]), true);
        auto f = [theta](float u) { return exp(theta * u); };
        // d I / d theta, from one backward with 4 samples.
        Var<T> I = integrate(f, UniformSampler{Sampler(7, uint64_t(s), 0)}, 4);
        I.backward();
        for (int c = 0; c < 3; ++c) value[c].add(double(I.value()[c]));
        for (int c = 0; c < 3; ++c) grad[c].add(double(theta.grad()[c]));
        // d I^2 / d theta = 2 I I': unbiased only with independent samples for I and I'.
        theta.zero_grad();
        Var<T> J = integrate(f, UniformSampler{Sampler(7, uint64_t(s), 1)}, 1);
        (J * J).backward();
        for (int c = 0; c < 3; ++c) grad_sq[c].add(double(theta.grad()[c]));
        // The same with the samples recorded (forward and backward share them): biased.
        theta.zero_grad();
        Sampler rng(7, uint64_t(s), 2);
        Var<T> K = f(rng.next_1d());
        (K * K).backward();
        for (int c = 0; c < 3; ++c) naive_sq[c].add(double(theta.grad()[c]));
    }
    for (int c = 0; c < 3; ++c) {
        CHECK_UNBIASED(value[c], I_exact(th[c]));
        CHECK_UNBIASED(grad[c], dI_exact(th[c]));
        CHECK_UNBIASED(grad_sq[c], 2 * I_exact(th[c]) * dI_exact(th[c]));
        // The test has the power to see the bias of reusing samples.
        double bias = naive_sq[c].mean() - 2 * I_exact(th[c]) * dI_exact(th[c]);
        CHECK(bias > 4 * naive_sq[c].standard_error());
    }
    // The value with many samples is close to the integral.
    tape_reset<T>();
    Var<T> theta(rgb<T>(th[0], th[1], th[2]), true);
    Var<T> I = integrate([theta](float u) { return exp(theta * u); },
                         UniformSampler{Sampler(11, 0, 0)}, 200000);
    for (int c = 0; c < 3; ++c) CHECK_CLOSE(I.value()[c], I_exact(th[c]), 0.01);
    tape_reset<T>();
}

/// I2(theta) = int_0^1 int_0^1 exp(theta x y) dy dx = sum_k theta^k / (k! (k+1)^2).
static double I2_exact(double t, bool derivative) {
    double sum = 0, term = 1;  // term = t^k / k!
    for (int k = 0; k < 60; ++k) {
        if (derivative) {
            if (k > 0) sum += k * term / t / ((k + 1.0) * (k + 1.0));
        } else {
            sum += term / ((k + 1.0) * (k + 1.0));
        }
        term *= t / (k + 1);
    }
    return sum;
}

template <typename T>
static void test12_nested_integrate() {
    g_test = "nested_integrate";
    const double th[3] = {0.5, 1.5, 3.0};
    const int runs = 3000;
    Stats value[3], grad[3];
    for (int s = 0; s < runs; ++s) {
        tape_reset<T>();
        Var<T> theta(rgb<T>(th[0], th[1], th[2]), true);
        uint64_t streams = 0;  // every inner integral draws from a stream of its own
        auto outer = [theta, s, &streams](float x) {
            auto inner = [theta, x](float y) { return exp(theta * (x * y)); };
            return integrate(inner, UniformSampler{Sampler(13, uint64_t(s), 1 + streams++)}, 2);
        };
        size_t n0 = tape_size<T>();
        Var<T> I = integrate(outer, UniformSampler{Sampler(13, uint64_t(s), 0)}, 2);
        CHECK(tape_size<T>() == n0 + 1);
        I.backward();
        CHECK(tape_size<T>() == n0 + 1);
        for (int c = 0; c < 3; ++c) value[c].add(double(I.value()[c]));
        for (int c = 0; c < 3; ++c) grad[c].add(double(theta.grad()[c]));
    }
    for (int c = 0; c < 3; ++c) {
        CHECK_UNBIASED(value[c], I2_exact(th[c], false));
        CHECK_UNBIASED(grad[c], I2_exact(th[c], true));
    }
    tape_reset<T>();
}

// ---- Main -----------------------------------------------------------------------------------

// ---- 5. Vectorisable math for the roughplastic tables (microfacet.h) -----------------------

/// exp_poly and erfc_poly against libm in double, and Beckmann's G1 from them (VectorMath)
/// against the libm form, both against G1 in double precision.
static void test13_vectorisable_math() {
    g_test = "vectorisable math";
    double worst_exp = 0.0, worst_erfc_near = 0.0, worst_erfc_far = 0.0;
    for (int i = 0; i <= 200000; ++i) {
        float x = -87.f + 97.f * float(i) / 200000.f;
        double ref = std::exp(double(x));
        worst_exp = std::max(worst_exp, std::abs(exp_poly(x) - ref) / ref);
        float z = 9.f * float(i) / 200000.f;
        double ref_c = std::erfc(double(z)), err = std::abs(erfc_poly(z) - ref_c) / ref_c;
        double &worst_erfc = z <= 2.f ? worst_erfc_near : worst_erfc_far;
        worst_erfc = std::max(worst_erfc, err);
    }
    CHECK(worst_exp < 1.2e-7);  // within 2 ulps (measured 1.7)
    // Numerical Recipes' 1.2e-7 plus float rounding (measured 5.2e-7); beyond z = 2 the
    // rounding of z^2 in float dominates (measured 7.7e-6), where erfc is below 5e-3.
    CHECK(worst_erfc_near < 1e-6);
    CHECK(worst_erfc_far < 1e-5);
    CHECK(exp_poly(-200.f) == exp_poly(-87.f));
    // G1 of Beckmann over roughness and directions: both forms within 2e-7 of double.
    double worst_poly = 0.0, worst_libm = 0.0;
    Vec3 m = normalize(Vec3(0.1f, -0.05f, 1.f));
    for (float alpha : {0.01f, 0.05f, 0.3f, 0.8f, 1.5f}) {
        for (int k = 1; k < 400; ++k) {
            float theta = 1.55f * float(k) / 400.f;
            Vec3 v(std::sin(theta), 0.f, std::cos(theta));
            double g_poly = smith_G1<MicrofacetType::Beckmann, true>(alpha, v, m);
            double g_libm = smith_G1<MicrofacetType::Beckmann>(alpha, v, m);
            double g_ref = smith_G1<MicrofacetType::Beckmann>(double(alpha), v, m);
            worst_poly = std::max(worst_poly, std::abs(g_poly - g_ref));
            worst_libm = std::max(worst_libm, std::abs(g_libm - g_ref));
        }
    }
    CHECK(worst_poly < 2e-7);
    CHECK(worst_libm < 2e-7);
    // GGX's G1 does not depend on the flag.
    Vec3 v = normalize(Vec3(0.7f, 0.2f, 0.4f));
    CHECK((smith_G1<MicrofacetType::GGX, true>(0.3f, v, m) == smith_G1<MicrofacetType::GGX>(0.3f, v, m)));
    // log_poly within 2 ulps of the exact log over normal floats (1e-30 to 1e30, and around
    // 1, where log is small); erfinv's inverse within Giles' 3e-7 plus rounding; acos_poly
    // within A&S's 2e-8 plus rounding.
    double worst_log = 0.0, worst_erfinv = 0.0, worst_acos = 0.0;
    for (int i = 0; i <= 200000; ++i) {
        float x = std::pow(10.f, -30.f + 60.f * float(i) / 200000.f);
        float near1 = 0.5f + float(i) / 200000.f;
        for (float y : {x, near1}) {
            double ref = std::log(double(y));
            double ulp = std::max(std::abs(ref), 1e-30) * 1.19e-7;  // (of the result)
            worst_log = std::max(worst_log, std::abs(log_poly(y) - ref) / ulp);
        }
        float u = -0.999999f + 1.999998f * float(i) / 200000.f;
        float e = erfinv(u);
        worst_erfinv = std::max(worst_erfinv, std::abs(std::erf(double(e)) - u) / std::max(1e-3, std::abs(double(u))));
        float c = float(i) / 200000.f;
        worst_acos = std::max(worst_acos, std::abs(acos_poly(c) - std::acos(double(c))));
    }
    CHECK(worst_log < 2.0);      // in ulps (measured 0.65)
    CHECK(worst_erfinv < 1e-6);  // (measured 2.4e-7)
    CHECK(worst_acos < 3e-7);    // (measured 2.4e-7)
    CHECK(std::isinf(erfinv(1.f)) && erfinv(1.f) > 0.f && std::isinf(erfinv(-1.f)) && erfinv(-1.f) < 0.f);
    CHECK(log_poly(1.f) == 0.f);
    // atan2_poly against double atan2 on directions all around the circle, at radii from tiny
    // to large, and on the axes (the quadrants' signs, atan2's at zero); acos_full over
    // [-1, 1] and clamped beyond.
    double worst_atan2 = 0.0, worst_acos_full = 0.0;
    for (int i = 0; i <= 200000; ++i) {
        double angle = -3.14159 + 6.28318 * double(i) / 200000.0;
        for (float r : {1e-20f, 1.f, 3e5f}) {
            float x = float(r * std::cos(angle)), y = float(r * std::sin(angle));
            worst_atan2 = std::max(worst_atan2, std::abs(atan2_poly(y, x) - std::atan2(double(y), double(x))));
        }
        float c = -1.f + 2.f * float(i) / 200000.f;
        worst_acos_full = std::max(worst_acos_full, std::abs(acos_full(c) - std::acos(double(c))));
    }
    CHECK(worst_atan2 < 4e-7);       // (measured 2.7e-7)
    CHECK(worst_acos_full < 5e-7);   // (measured 4.0e-7: pi - acos_poly near -1)
    for (float s : {1.f, -1.f}) {
        CHECK(atan2_poly(0.f * s, 1.f) == 0.f && std::signbit(atan2_poly(0.f * s, 1.f)) == (s < 0.f));
        CHECK(std::abs(atan2_poly(0.f * s, -1.f) - s * 3.14159265f) < 4e-7f);
        CHECK(std::abs(atan2_poly(s, 0.f) - s * 1.57079633f) < 4e-7f);
        CHECK(std::abs(atan2_poly(s, 1.f) - s * 0.78539816f) < 4e-7f && std::abs(atan2_poly(s, -1.f) - s * 2.35619449f) < 4e-7f);
    }
    CHECK(atan2_poly(0.f, 0.f) == 0.f);
    CHECK(acos_full(1.f) == 0.f && std::abs(acos_full(-1.f) - 3.14159265f) < 4e-7f);
    CHECK(acos_full(1.5f) == acos_full(1.f) && acos_full(-1.5f) == acos_full(-1.f));
    // A bilinear lookup's pair of wrapped texel indices, with one division: the indices
    // wrap_index gives i and i + 1, in every mode and size, for i on both sides of zero.
    bool pairs_agree = true;
    for (WrapMode mode : {WrapMode::Repeat, WrapMode::Mirror, WrapMode::Clamp}) {
        Bitmap bm;
        bm.wrap = mode;
        for (int n : {1, 2, 3, 5, 8}) {
            for (int i = -50; i <= 50; ++i) {
                int64_t w0 = -1, w1 = -1;
                bm.wrap_pair(i, n, &w0, &w1);
                pairs_agree = pairs_agree && w0 == bm.wrap_index(i, n) && w1 == bm.wrap_index(i + 1, n);
            }
        }
    }
    CHECK(pairs_agree);
}

/// microfacet_dlog_dalpha's closed form (float, the polynomials) against a dual number in double
/// through microfacet_D and smith_G1 (libm): D(h) G1(wi, h) G1(wo, h) and d log / d alpha, over
/// roughness from near-mirror to very rough and directions over the hemisphere, grazing ones
/// and wi = wo among them, and zero where the value is.
static void test15_microfacet_dlog() {
    g_test = "microfacet d log / d alpha";
    uint64_t state = 12345;
    auto uniform = [&]() {
        state = state * 6364136223846793005ull + 1442695040888963407ull;
        return float(state >> 40) / float(1ull << 24);
    };
    auto direction = [&]() {
        float z = uniform(), phi = 6.2831853f * uniform(), r = std::sqrt(std::max(0.f, 1.f - z * z));
        return Vec3(r * std::cos(phi), r * std::sin(phi), z);
    };
    double worst_value = 0.0, worst_dlog = 0.0;
    int zeros = 0, nonzero = 0, zeros_disagree = 0;
    for (MicrofacetType type : {MicrofacetType::Beckmann, MicrofacetType::GGX}) {
        for (float alpha : {0.005f, 0.02f, 0.1f, 0.3f, 0.8f, 1.5f}) {
            for (int i = 0; i < 20000; ++i) {
                Vec3 wi = direction(), wo = i % 7 == 0 ? wi : direction();
                if (i % 11 == 0) wo = normalize(Vec3(wo.x, wo.y, 1e-3f));  // grazing
                if (!(wi.z > 0.f && wo.z > 0.f)) continue;
                const Vec3 h = normalize(wi + wo);
                const FactorDlog ours = microfacet_dlog_dalpha(type, alpha, wi, wo, h);
                const Dual<double> a(RGB<double>(double(alpha)), RGB<double>(1.0));
                const Dual<double> f = microfacet_D(type, a, h) * smith_G1(type, a, wi, h) * smith_G1(type, a, wo, h);
                const double value = f.v[0], dlog = value != 0.0 ? f.d[0] / value : 0.0;
                if (ours.value == 0.f || value == 0.0) {
                    ++zeros;
                    // (The float D stops at e^-87, the double one at e^-150: both negligible.)
                    zeros_disagree += (ours.value == 0.f) != (value == 0.0) && std::max(double(ours.value), value) > 1e-30;
                    CHECK(ours.value != 0.f || ours.dlog == 0.f);
                    continue;
                }
                ++nonzero;
                worst_value = std::max(worst_value, std::abs(ours.value - value) / value);
                // Relative to the sum of the terms' sizes (d log D cancels where tan^2 = alpha^2).
                const float xy2 = h.x * h.x + h.y * h.y, cos2 = h.z * h.z;
                const double scale = 2.0 / alpha * (1.0 + 2.0 * xy2 / cos2 / (double(alpha) * alpha)) + std::abs(dlog);
                worst_dlog = std::max(worst_dlog, std::abs(ours.dlog - dlog) / scale);
            }
        }
    }
    CHECK(nonzero > 150000 && zeros > 0);
    CHECK(zeros_disagree == 0);
    CHECK(worst_value < 2e-5);  // (measured 3.9e-6: exp_poly and erfc_poly against libm)
    CHECK(worst_dlog < 1e-6);   // (measured 9.0e-8)
}

// ---- 5. Sink nodes: parameter reads that scatter into a gradient buffer ---------------------

template <typename T>
static void test14_sink_nodes() {
    g_test = "sink_nodes";
    tape_reset<T>();
    Var<T> x(rgb<T>(1, 2, 3), true);
    // A bilinear read of four RGB texels and a constant read of one channel (which receives
    // the sum of the adjoint's channels), both twice, so that their deposits add up.
    std::vector<double> texel_grads(16 * 3, 0.0), scalar_grad(1, 0.0);
    const int64_t offset[4] = {0, 3, 12, 15};
    const float weight[4] = {0.1f, 0.2f, 0.3f, 0.4f};
    RGB<T> tv = rgb<T>(0.5, 0.25, 0.125), sv(T(0.75));
    Var<T> texture(tv, texel_grads.data(), 3, 4, offset, weight);
    Var<T> scalar(sv, scalar_grad.data(), 1);
    CHECK(texture.requires_grad() && scalar.requires_grad());
    CHECK_RGB(texture.value(), tv, 0);
    Var<T> y = texture * x + scalar * texture + Var<T>(tv, texel_grads.data(), 3, 4, offset, weight) +
               Var<T>(sv, scalar_grad.data(), 1) * 2.f;
    y.backward(rgb<T>(1, 10, 100));
    RGB<T> seed = rgb<T>(1, 10, 100);
    RGB<T> d_texture = seed * (x.value() + sv) + seed;  // both reads of the texels
    for (int k = 0; k < 4; ++k)
        for (int c = 0; c < 3; ++c)
            CHECK_CLOSE(texel_grads[size_t(offset[k] + c)], double(weight[k]) * double(d_texture[c]),
                        tolerance<T>());
    CHECK_CLOSE(texel_grads[6], 0.0, 0.0);  // untouched entries stay zero
    RGB<T> d_scalar = seed * tv + seed * T(2);
    CHECK_CLOSE(scalar_grad[0], double(d_scalar[0]) + double(d_scalar[1]) + double(d_scalar[2]),
                tolerance<T>());
    CHECK_RGB(x.grad(), seed * tv, tolerance<T>());

    // Under NoRecord a read is a constant; a rewind drops the sinks recorded after its mark.
    {
        NoRecord no_record;
        CHECK(!Var<T>(tv, scalar_grad.data(), 1).requires_grad());
    }
    double before = scalar_grad[0];
    tape_reset<T>();
    Var<T> again(sv, scalar_grad.data(), 1);
    (again * 3.f).backward();
    CHECK_CLOSE(scalar_grad[0], before + 9.0, tolerance<T>());

    // A read inside a custom functor's backward step is swept there and discarded after.
    tape_reset<T>();
    scalar_grad[0] = 0.0;
    Var<T> z(x, [&](const RGB<T> &g) {
        Var<T> inner(sv, scalar_grad.data(), 1);
        (inner * inner).backward(g);
    });
    Var<T> w = z * 2.f;
    size_t size = tape_size<T>();
    w.backward();
    CHECK(tape_size<T>() == size);
    CHECK_CLOSE(scalar_grad[0], 3.0 * 2.0 * 2.0 * double(sv[0]), tolerance<T>());
}

template <typename T>
static void run_var_tests() {
    test01_operations<Var<T>>();
    test02_composites<Var<T>>();
    test04_microfacet<Var<T>>();
    test05_constants_record_nothing<T>();
    test06_accumulation_and_diamond<T>();
    test07_custom_functors<T>();
    test08_reuse_without_allocation<T>();
    test09_long_chains<T>();
    test10_integrate_uses_new_samples<T>();
    test11_integrate_is_unbiased<T>();
    test12_nested_integrate<T>();
    test14_sink_nodes<T>();
}

int main() {
    run_var_tests<float>();
    run_var_tests<double>();
    test01_operations<Dual<float>>();
    test01_operations<Dual<double>>();
    test02_composites<Dual<double>>();
    test04_microfacet<Dual<double>>();
    test04_microfacet<Dual<float>>();
    test03_var_matches_dual();
    test13_vectorisable_math();
    test15_microfacet_dlog();
    std::printf("%d passed, %d failed\n", g_passed, g_failed);
    return g_failed == 0 ? 0 : 1;
}
