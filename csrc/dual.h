// Forward-mode automatic differentiation: Dual<T>, an RGB value with an RGB tangent (dual
// numbers, TR-21-05 section 4), used to validate the reverse-mode gradients of Var<T> by
// running the same path tracer code. One directional derivative per run: seed the tangent of
// the parameter being differentiated (e.g. 1 in one channel) and read the result's tangent.
//
// Design: a plain value type (no tape, no allocation); every operation is componentwise, so
// channel c of the tangent is the derivative of channel c of the value. Scalars are Duals with
// equal channels (real_t<Dual<T>> = Dual<T>); arithmetic and RGB<T> values convert implicitly
// to constants (zero tangent).
#pragma once

#include <cmath>
#include <type_traits>

#include "math.h"

namespace rbpt {

/// Dual RGB number: value v and tangent d (the derivative of v along the seeded direction).
template <typename T>
struct Dual {
    using Scalar = T;

    RGB<T> v;  ///< value
    RGB<T> d;  ///< tangent

    /// The constant 0.
    Dual() = default;
    /// A constant scalar broadcast to RGB (implicit, so that `x * 0.5f`, `1.f - x` work).
    template <typename U, std::enable_if_t<std::is_arithmetic_v<U> && !std::is_same_v<U, bool>,
                                           int> = 0>
    Dual(U s) : v(T(s)) {}  // NOLINT: implicit by design
    /// A constant RGB value.
    Dual(const RGB<T> &value) : v(value) {}  // NOLINT: implicit by design
    /// A value with a tangent (`Dual(x, 1)` seeds d/dx in every channel).
    Dual(const RGB<T> &value, const RGB<T> &tangent) : v(value), d(tangent) {}

    /// The value.
    const RGB<T> &value() const { return v; }
    /// The tangent (directional derivative).
    const RGB<T> &tangent() const { return d; }
    /// A constant with the same value. (The free detach() of math.h gives a Color3f.)
    Dual detach() const { return Dual(v); }

    /// Componentwise arithmetic; scalars and RGB<T> operands convert to constants.
    friend Dual operator+(const Dual &a, const Dual &b) { return {a.v + b.v, a.d + b.d}; }
    friend Dual operator-(const Dual &a, const Dual &b) { return {a.v - b.v, a.d - b.d}; }
    friend Dual operator*(const Dual &a, const Dual &b) {
        return {a.v * b.v, a.d * b.v + a.v * b.d};
    }
    friend Dual operator/(const Dual &a, const Dual &b) {
        RGB<T> q = a.v / b.v;
        return {q, (a.d - q * b.d) / b.v};
    }
    friend Dual operator-(const Dual &a) { return {T(-1) * a.v, T(-1) * a.d}; }
    /// Compound assignment.
    Dual &operator+=(const Dual &b) { return *this = *this + b; }
    Dual &operator-=(const Dual &b) { return *this = *this - b; }
    Dual &operator*=(const Dual &b) { return *this = *this * b; }
    Dual &operator/=(const Dual &b) { return *this = *this / b; }
};

namespace detail {

/// Dual of componentwise f with derivative df: {f(v), df(v) d}.
template <typename T, typename F, typename DF>
inline Dual<T> dual_map(const Dual<T> &x, F f, DF df) {
    Dual<T> r;
    for (int i = 0; i < 3; ++i) {
        r.v.v[i] = f(x.v.v[i]);
        r.d.v[i] = df(x.v.v[i], r.v.v[i]) * x.d.v[i];
    }
    return r;
}

}  // namespace detail

/// Componentwise e^x.
template <typename T>
Dual<T> exp(const Dual<T> &x) {
    return detail::dual_map(x, [](T a) { return std::exp(a); }, [](T, T e) { return e; });
}
/// Componentwise natural logarithm.
template <typename T>
Dual<T> log(const Dual<T> &x) {
    return detail::dual_map(x, [](T a) { return std::log(a); }, [](T a, T) { return T(1) / a; });
}
/// Componentwise square root (infinite derivative at 0).
template <typename T>
Dual<T> sqrt(const Dual<T> &x) {
    return detail::dual_map(
        x, [](T a) { return std::sqrt(a); }, [](T, T s) { return T(0.5) / s; });
}
/// Componentwise error function; d erf(x) = 2/sqrt(pi) e^(-x^2).
template <typename T>
Dual<T> erf(const Dual<T> &x) {
    return detail::dual_map(
        x, [](T a) { return std::erf(a); },
        [](T a, T) { return T(1.1283791670955126) * std::exp(-a * a); });
}
/// Componentwise x^p for a constant exponent p.
template <typename T>
Dual<T> pow(const Dual<T> &x, typename Dual<T>::Scalar p) {
    return detail::dual_map(
        x, [p](T a) { return std::pow(a, p); },
        [p](T a, T) { return p * std::pow(a, p - T(1)); });
}
/// Componentwise |x| (derivative sign(x), 0 at 0).
template <typename T>
Dual<T> abs(const Dual<T> &x) {
    return detail::dual_map(
        x, [](T a) { return std::abs(a); }, [](T a, T) { return T((a > T(0)) - (a < T(0))); });
}
/// Componentwise minimum; each channel's tangent is the selected operand's (a on ties).
template <typename T>
Dual<T> min(const Dual<T> &a, const Dual<T> &b) {
    Dual<T> r;
    for (int i = 0; i < 3; ++i) {
        bool pick_a = a.v.v[i] <= b.v.v[i];
        r.v.v[i] = pick_a ? a.v.v[i] : b.v.v[i];
        r.d.v[i] = pick_a ? a.d.v[i] : b.d.v[i];
    }
    return r;
}
/// Componentwise maximum; each channel's tangent is the selected operand's (a on ties).
template <typename T>
Dual<T> max(const Dual<T> &a, const Dual<T> &b) {
    Dual<T> r;
    for (int i = 0; i < 3; ++i) {
        bool pick_a = a.v.v[i] >= b.v.v[i];
        r.v.v[i] = pick_a ? a.v.v[i] : b.v.v[i];
        r.d.v[i] = pick_a ? a.d.v[i] : b.d.v[i];
    }
    return r;
}
/// min of a Dual and a constant scalar (broadcast).
template <typename T>
Dual<T> min(const Dual<T> &a, typename Dual<T>::Scalar b) {
    return min(a, Dual<T>(b));
}
/// min of a constant scalar and a Dual.
template <typename T>
Dual<T> min(typename Dual<T>::Scalar a, const Dual<T> &b) {
    return min(Dual<T>(a), b);
}
/// max of a Dual and a constant scalar.
template <typename T>
Dual<T> max(const Dual<T> &a, typename Dual<T>::Scalar b) {
    return max(a, Dual<T>(b));
}
/// max of a constant scalar and a Dual.
template <typename T>
Dual<T> max(typename Dual<T>::Scalar a, const Dual<T> &b) {
    return max(Dual<T>(a), b);
}
/// A constant with the value of x (generic spelling of x.detach()).
template <typename T>
Dual<T> no_grad(const Dual<T> &x) {
    return x.detach();
}

/// Traits for the path tracer: scalars are Duals; detach() gives the value as a Color3f.
template <typename T>
struct SpectrumTraits<Dual<T>> {
    using Real = Dual<T>;  ///< scalars are RGB with equal channels
    static Color3f detach(const Dual<T> &s) { return SpectrumTraits<RGB<T>>::detach(s.v); }
    /// Whether the value is finite (as Var: the render loop drops the same samples).
    static bool is_finite(const Dual<T> &s) { return SpectrumTraits<RGB<T>>::is_finite(s.v); }
    static bool has_derivative(const Dual<T> &s) {
        return s.d[0] != T(0) || s.d[1] != T(0) || s.d[2] != T(0);
    }
};

/// Value of a scalar Dual (its first channel), without derivatives.
template <typename T>
inline float detach_real(const Dual<T> &x) {
    return float(x.v.v[0]);
}

}  // namespace rbpt
