// Status codes of the no-throw API and of every parameter check (a code plus a static message).
#pragma once

#include <cstdint>

namespace miem {

/// What went wrong, if anything.
enum class StatusCode : std::uint8_t {
  kOk = 0,
  kInvalidParameter = 1,  ///< a parameter field (or the stream width) is out of range or unsupported
  kInvalidInput = 2,      ///< null data or output, an empty view
  kTooFewPoints = 3,      ///< fewer than 3 finite points
  kDegenerate = 4,        ///< points all equal or collinear: no plane
  kWrongWidth = 5,        ///< stream: profile size differs from the stream width (rejected)
  kEmptyProfile = 6,      ///< stream: no finite point (taken as a row of dropouts)
  kFinished = 7,          ///< stream: push after flush; call reset() to start a new stream
  kOutOfMemory = 8,       ///< an allocation failed
  kInternal = 9,          ///< an unexpected exception (a bug: please report it)
};

/// A status: a code and a static, human-readable message (never freed, never allocated) that
/// starts with the name of the offending argument or field.
struct Status {
  StatusCode code = StatusCode::kOk;
  const char* message = "ok";

  /// True for StatusCode::kOk only.
  bool ok() const noexcept { return code == StatusCode::kOk; }
  explicit operator bool() const noexcept { return ok(); }
};

/// "ok", "invalid parameter", ... for a code.
const char* to_string(StatusCode code) noexcept;

/// Throws std::invalid_argument with the status message unless `st` is ok (the throwing API's
/// side of every check()).
void throw_if_error(const Status& st);

}  // namespace miem
