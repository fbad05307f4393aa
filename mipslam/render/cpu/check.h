// Argument checks of the C interface (api.cpp): a failed check throws, and the exported function that
// called it returns an error code with the message (mipslam/render/cpu/library.py raises it in Python).
#pragma once

#include <sstream>
#include <stdexcept>
#include <string>

namespace mipslam_cpu {

template <typename... Parts>
static std::string join_message(const Parts&... parts) {
    std::ostringstream out;
    (out << ... << parts);
    return out.str();
}

}  // namespace mipslam_cpu

// A broken internal invariant or an unsupported size: RuntimeError in Python.
#define MIPSLAM_CHECK(cond, ...) \
    do {                                                                                        \
        if (!(cond)) throw std::runtime_error(::mipslam_cpu::join_message(__VA_ARGS__));         \
    } while (0)

// An invalid value from the caller (a bad camera): RenderError in Python.
#define MIPSLAM_CHECK_VALUE(cond, ...) \
    do {                                                                                        \
        if (!(cond)) throw std::invalid_argument(::mipslam_cpu::join_message(__VA_ARGS__));      \
    } while (0)
