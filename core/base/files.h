// Files: reading one whole, recognising and listing images, and the natural order of file names.
//
// The one definition of each for every tool, command and test, so that a folder of frames is
// read in the same order and with the same image set by placedb, placedb-recognize, the
// evaluation and the vocabulary tools.
#pragma once

#include <filesystem>
#include <string>
#include <string_view>
#include <vector>

#include "core/base/status.h"

namespace placedb {

// The contents of the file at `path`, read to its end. NotFound when nothing is there; IoError
// naming the path and the system's reason when it cannot be opened or read (a directory, no
// permission); ResourceExhausted when it does not fit in memory.
Result<std::string> ReadWholeFile(const std::string& path);

// True when `path` names an image by its extension, compared case-insensitively: .jpg .jpeg .png
// .bmp .pgm .ppm .pnm .tif .tiff .webp (what OpenCV decodes on Debian).
bool IsImageFile(const std::filesystem::path& path);

// Natural order of names: digit runs compare by value ("frame9" < "frame10" < "frame11"),
// everything else byte by byte. Equal values with different leading zeros
// compare by the run's length, shorter first ("frame7" < "frame07" < "frame007"), so the order is
// total: two names are equivalent only when they are equal.
bool NaturalLess(std::string_view a, std::string_view b);

// The image files (IsImageFile, regular files only) directly in `directory`, as paths joined to
// `directory`, sorted by NaturalLess of their file names. NotFound when `directory` is not a
// directory, IoError when it cannot be listed; an empty vector when it holds no images (each
// caller words that error for its own input).
Result<std::vector<std::string>> ListImageFiles(const std::string& directory);

}  // namespace placedb
