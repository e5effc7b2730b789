// Vocabulary file formats: the checksummed binary ".pdbv" and DBoW2/DBoW3 text (ORBvoc.txt).
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstddef>
#include <cstring>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "core/base/files.h"
#include "core/vocabulary/vocabulary.h"

namespace placedb {

static_assert(std::endian::native == std::endian::little,
              "the binary vocabulary format is little-endian; add byte swapping for this target");

namespace {

constexpr char kMagic[8] = {'P', 'L', 'D', 'B', 'V', 'O', 'C', '\0'};
constexpr uint32_t kFormatVersion = 1;

// The fixed 64-byte header of a binary vocabulary; the block follows it verbatim.
struct FileHeader {
  char magic[8];
  uint32_t version;
  uint32_t header_bytes;  // sizeof(FileHeader): where the block starts
  int32_t branching;
  int32_t depth;
  int32_t scoring;
  int32_t weighting;
  uint32_t node_count;
  uint32_t word_count;
  uint64_t block_bytes;
  uint64_t checksum;         // Checksum64 of the block: the vocabulary's identity
  uint64_t header_checksum;  // Checksum64 of the bytes before this field
};
static_assert(sizeof(FileHeader) == 64);
constexpr size_t kHeaderChecksummedBytes = offsetof(FileHeader, header_checksum);

// Checksum64: four independent lanes, each absorbing one 64-bit word per 32-byte stripe with an
// xor, a multiply by an odd constant (a bijection, so no single-word change can cancel) and a
// rotation (brings the well-mixed high bits down). Lanes are folded and avalanched at the end.
// Incremental, so a load can hash each chunk while it is still in cache.
class ChecksumState {
 public:
  explicit ChecksumState(uint64_t seed)
      : lane_{seed ^ 0x243f6a8885a308d3ull, seed + 0x13198a2e03707344ull,
              ~seed ^ 0xa4093822299f31d0ull, seed - 0x082efa98ec4e6c89ull} {}

  // `bytes` must be a multiple of 32 except in the last call.
  void Update(const void* data, size_t bytes) {
    const auto* p = static_cast<const uint8_t*>(data);
    total_ += bytes;
    uint64_t l0 = lane_[0], l1 = lane_[1], l2 = lane_[2], l3 = lane_[3];
    for (size_t stripes = bytes / 32; stripes > 0; --stripes, p += 32) {
      l0 = Absorb(l0, Load64(p), 0);
      l1 = Absorb(l1, Load64(p + 8), 1);
      l2 = Absorb(l2, Load64(p + 16), 2);
      l3 = Absorb(l3, Load64(p + 24), 3);
    }
    if (const size_t tail = bytes % 32; tail != 0) {
      uint8_t last[32] = {};
      std::memcpy(last, p, tail);
      l0 = Absorb(l0, Load64(last), 0);
      l1 = Absorb(l1, Load64(last + 8), 1);
      l2 = Absorb(l2, Load64(last + 16), 2);
      l3 = Absorb(l3, Load64(last + 24), 3);
    }
    lane_[0] = l0, lane_[1] = l1, lane_[2] = l2, lane_[3] = l3;
  }

  uint64_t Finish() const {
    uint64_t h = uint64_t(total_) * kFoldMul;
    for (int i = 0; i < 4; ++i) h = std::rotl((h ^ lane_[i]) * kFoldMul, 23 + 7 * i);
    h ^= h >> 31;
    h *= kFinalMul1;
    h ^= h >> 29;
    h *= kFinalMul2;
    h ^= h >> 32;
    return h;
  }

 private:
  static constexpr uint64_t kLaneMul[4] = {0xd1a6e55e9b9b1325ull, 0x566bf9d7c55a45f9ull,
                                           0xcf0c26ef4243ed53ull, 0x5d96cf7f265beda9ull};
  static constexpr uint64_t kFoldMul = 0xc1d77cffb7decc0dull;
  static constexpr uint64_t kFinalMul1 = 0x5e6a0a2edd70e34dull;
  static constexpr uint64_t kFinalMul2 = 0xb37523a53b4a3ee3ull;

  static uint64_t Load64(const uint8_t* p) {
    uint64_t v;
    std::memcpy(&v, p, 8);
    if constexpr (std::endian::native == std::endian::big) v = __builtin_bswap64(v);
    return v;
  }
  static uint64_t Absorb(uint64_t lane, uint64_t word, int lane_index) {
    return std::rotl((lane ^ word) * kLaneMul[lane_index], 29);
  }

  uint64_t lane_[4];
  uint64_t total_ = 0;
};

std::string Errno(const std::string& what, const std::string& path) {
  return what + " " + path + ": " + std::strerror(errno);
}

// Closes a file descriptor on scope exit.
class FileDescriptor {
 public:
  explicit FileDescriptor(int fd) : fd_(fd) {}
  ~FileDescriptor() {
    if (fd_ >= 0) ::close(fd_);
  }
  FileDescriptor(const FileDescriptor&) = delete;
  FileDescriptor& operator=(const FileDescriptor&) = delete;
  int get() const { return fd_; }
  int release() { return std::exchange(fd_, -1); }

 private:
  int fd_;
};

Result<int> OpenForReading(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    if (errno == ENOENT) return Status::NotFound("no such file: " + path);
    return Status::IoError(Errno("cannot open", path));
  }
  return fd;
}

// Reads up to `bytes`; returns how many were read (fewer only at end of file).
Result<size_t> ReadFully(int fd, void* buffer, size_t bytes, const std::string& path) {
  size_t done = 0;
  auto* out = static_cast<char*>(buffer);
  while (done < bytes) {
    // Linux transfers at most ~2 GiB per call.
    const size_t chunk = std::min<size_t>(bytes - done, size_t{1} << 30);
    const ssize_t got = ::read(fd, out + done, chunk);
    if (got < 0) {
      if (errno == EINTR) continue;
      return Status::IoError(Errno("cannot read", path));
    }
    if (got == 0) break;
    done += size_t(got);
  }
  return done;
}

Status WriteFully(int fd, const void* data, size_t bytes, const std::string& path) {
  const auto* in = static_cast<const char*>(data);
  while (bytes > 0) {
    const ssize_t put = ::write(fd, in, std::min<size_t>(bytes, size_t{1} << 30));
    if (put < 0) {
      if (errno == EINTR) continue;
      return Status::IoError(Errno("cannot write", path));
    }
    in += put;
    bytes -= size_t(put);
  }
  return Status::Ok();
}

struct Piece {
  const void* data;
  size_t bytes;
};

// Writes `pieces` to a temporary file next to `path`, syncs it and renames it over `path`, so a
// reader sees the old file or the complete new one, never a partial one.
Status WriteFileAtomically(const std::string& path, std::initializer_list<Piece> pieces) {
  static std::atomic<uint64_t> counter{0};
  const std::string temp =
      path + ".tmp." + std::to_string(::getpid()) + "." + std::to_string(counter.fetch_add(1));
  FileDescriptor fd(::open(temp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644));
  if (fd.get() < 0) return Status::IoError(Errno("cannot create", temp));
  Status status;
  for (const Piece& piece : pieces) {
    status = WriteFully(fd.get(), piece.data, piece.bytes, temp);
    if (!status.ok()) break;
  }
  if (status.ok() && ::fsync(fd.get()) != 0) status = Status::IoError(Errno("cannot sync", temp));
  if (::close(fd.release()) != 0 && status.ok()) {
    status = Status::IoError(Errno("cannot close", temp));
  }
  if (status.ok() && ::rename(temp.c_str(), path.c_str()) != 0) {
    status = Status::IoError(Errno("cannot rename " + temp + " to", path));
  }
  if (!status.ok()) ::unlink(temp.c_str());
  return status;
}

// ---- DBoW2 text parsing --------------------------------------------------------------------

bool IsBlank(char c) {
  return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f';
}

// Tokenises one line (without its '\n') and parses numbers without allocating.
class LineParser {
 public:
  LineParser(std::string_view line, size_t line_number) : line_(line), number_(line_number) {}

  // Next whitespace-separated token, empty at the end of the line.
  std::string_view Token() {
    while (pos_ < line_.size() && IsBlank(line_[pos_])) ++pos_;
    const size_t begin = pos_;
    while (pos_ < line_.size() && !IsBlank(line_[pos_])) ++pos_;
    return line_.substr(begin, pos_ - begin);
  }

  template <typename Int>
  Status Integer(const char* what, Int* value) {
    const std::string_view token = Token();
    if (token.empty()) return Error(std::string("missing ") + what);
    const auto [end, error] = std::from_chars(token.data(), token.data() + token.size(), *value);
    if (error != std::errc() || end != token.data() + token.size()) {
      return Error(std::string("bad ") + what + " '" + std::string(token) + "'");
    }
    return Status::Ok();
  }

  // A decimal number in [0, max], parsed by hand: this is the hot loop of a text import (34
  // numbers per node), so the fast path returns a bool and only a failure builds a message. No
  // bounds checks: every line is followed by '\n' or the text's terminating NUL, which stop both
  // loops (see ParseDbow2Text).
  bool Unsigned(uint32_t max, uint32_t* value) {
    const char* p = line_.data() + pos_;
    while (IsBlank(*p)) ++p;
    const char* begin = p;
    uint64_t number = 0;
    while (unsigned(*p - '0') < 10 && p - begin < 11) number = number * 10 + unsigned(*p++ - '0');
    if (p == begin || number > max || !(IsBlank(*p) || p == line_.data() + line_.size())) {
      return false;
    }
    pos_ = size_t(p - line_.data());
    *value = uint32_t(number);
    return true;
  }
  // The error for the token Unsigned() just rejected.
  Status UnsignedError(const char* what, uint32_t max) {
    const std::string_view token = Token();
    if (token.empty()) return Error(std::string("missing ") + what);
    return Error(std::string("bad ") + what + " '" + std::string(token) + "' (expected 0.." +
                 std::to_string(max) + ")");
  }

  Status Float(const char* what, float* value) {
    const std::string_view token = Token();
    if (token.empty()) return Error(std::string("missing ") + what);
    const auto [end, error] = std::from_chars(token.data(), token.data() + token.size(), *value);
    if (error != std::errc() || end != token.data() + token.size() || !std::isfinite(*value)) {
      return Error(std::string("bad ") + what + " '" + std::string(token) + "'");
    }
    return Status::Ok();
  }

  Status ExpectEnd() {
    const std::string_view token = Token();
    if (!token.empty()) return Error("unexpected extra field '" + std::string(token) + "'");
    return Status::Ok();
  }

  Status Error(const std::string& message) const {
    return Status::Corruption("line " + std::to_string(number_) + ": " + message);
  }

 private:
  std::string_view line_;
  size_t number_;
  size_t pos_ = 0;
};

bool IsBlankLine(std::string_view line) {
  for (char c : line) {
    if (!IsBlank(c)) return false;
  }
  return true;
}

// `text` must be followed in memory by a NUL (std::string guarantees it): LineParser relies on it.
Result<VocabularyTree> ParseDbow2Text(std::string_view text) {
  if (text.find('\0') != std::string_view::npos) {
    return Status::Corruption("not a DBoW2 text vocabulary (the file contains NUL bytes)");
  }
  // Lines: the last non-blank one ends the content; blank lines after it are tolerated.
  std::vector<std::string_view> lines;
  {
    size_t begin = 0;
    while (begin < text.size()) {
      size_t end = text.find('\n', begin);
      if (end == std::string_view::npos) end = text.size();
      lines.push_back(text.substr(begin, end - begin));
      begin = end + 1;
    }
    while (!lines.empty() && IsBlankLine(lines.back())) lines.pop_back();
  }
  if (lines.empty()) return Status::Corruption("the file is empty");

  VocabularyTree tree;
  {
    LineParser header(lines[0], 1);
    int scoring = 0;
    int weighting = 0;
    PLACEDB_RETURN_IF_ERROR(header.Integer("k", &tree.branching));
    PLACEDB_RETURN_IF_ERROR(header.Integer("L", &tree.depth));
    PLACEDB_RETURN_IF_ERROR(header.Integer("scoring type", &scoring));
    PLACEDB_RETURN_IF_ERROR(header.Integer("weighting type", &weighting));
    PLACEDB_RETURN_IF_ERROR(header.ExpectEnd());
    if (tree.branching < 2 || tree.branching > 1024) {
      return header.Error("k must be in [2, 1024], got " + std::to_string(tree.branching));
    }
    if (tree.depth < 1 || tree.depth > 32) {
      return header.Error("L must be in [1, 32], got " + std::to_string(tree.depth));
    }
    if (scoring < 0 || scoring > 5) {
      return header.Error("unknown scoring type " + std::to_string(scoring));
    }
    if (weighting < 0 || weighting > 3) {
      return header.Error("unknown weighting type " + std::to_string(weighting));
    }
    tree.scoring = static_cast<ScoringType>(scoring);
    tree.weighting = static_cast<WeightingType>(weighting);
  }
  const size_t n = lines.size();  // the root plus one node per line after the header
  if (n < 2) return Status::Corruption("line 2: the vocabulary has no nodes");
  if (n >= size_t{Vocabulary::kNoWord}) return Status::Corruption("too many nodes");
  tree.parent.assign(n, 0);
  tree.descriptor.assign(n, Descriptor256{});
  tree.weight.assign(n, 0.0f);
  tree.word_id.assign(n, -1);
  std::vector<uint8_t> is_leaf(n, 0);
  std::vector<uint32_t> children(n, 0);
  std::vector<uint8_t> level(n, 0);
  int32_t words = 0;
  for (size_t node = 1; node < n; ++node) {
    const size_t line_number = node + 1;
    if (IsBlankLine(lines[node])) {
      return Status::Corruption("line " + std::to_string(line_number) +
                                ": empty line inside the node list");
    }
    LineParser line(lines[node], line_number);
    uint32_t parent = 0;
    uint32_t leaf = 0;
    if (!line.Unsigned(Vocabulary::kNoWord - 1, &parent)) {
      return line.UnsignedError("parent id", Vocabulary::kNoWord - 1);
    }
    if (!line.Unsigned(1, &leaf)) return line.UnsignedError("leaf flag", 1);
    if (parent >= node) {
      return line.Error("parent " + std::to_string(parent) + " of node " + std::to_string(node) +
                        " is not an earlier node");
    }
    if (is_leaf[parent]) return line.Error("parent " + std::to_string(parent) + " is a leaf");
    if (++children[parent] > uint32_t(tree.branching)) {
      return line.Error("node " + std::to_string(parent) +
                        " has more than k = " + std::to_string(tree.branching) + " children");
    }
    level[node] = uint8_t(level[parent] + 1);
    if (level[node] > tree.depth) {
      return line.Error("node " + std::to_string(node) +
                        " is deeper than L = " + std::to_string(tree.depth));
    }
    uint8_t bytes[Descriptor256::kBytes];
    for (int b = 0; b < Descriptor256::kBytes; ++b) {
      uint32_t value = 0;
      if (!line.Unsigned(255, &value)) return line.UnsignedError("descriptor byte", 255);
      bytes[b] = uint8_t(value);
    }
    PLACEDB_RETURN_IF_ERROR(line.Float("weight", &tree.weight[node]));
    PLACEDB_RETURN_IF_ERROR(line.ExpectEnd());
    tree.parent[node] = parent;
    tree.descriptor[node] = Descriptor256::FromBytes(bytes);
    is_leaf[node] = uint8_t(leaf);
    if (leaf) tree.word_id[node] = words++;  // DBoW2 numbers words in file order
  }
  for (size_t node = 0; node < n; ++node) {
    if (!is_leaf[node] && children[node] == 0) {
      return Status::Corruption("line " + std::to_string(node + 1) + ": node " +
                                std::to_string(node) + " is not a leaf but has no children");
    }
  }
  return tree;
}

// Decimal text of 0..255 followed by a space, for fast export.
struct ByteText {
  char text[4];
  uint8_t length;
};
constexpr std::array<ByteText, 256> MakeByteTexts() {
  std::array<ByteText, 256> table{};
  for (int value = 0; value < 256; ++value) {
    ByteText& entry = table[value];
    uint8_t length = 0;
    if (value >= 100) entry.text[length++] = char('0' + value / 100);
    if (value >= 10) entry.text[length++] = char('0' + value / 10 % 10);
    entry.text[length++] = char('0' + value % 10);
    entry.text[length++] = ' ';
    entry.length = length;
  }
  return table;
}
constexpr std::array<ByteText, 256> kByteTexts = MakeByteTexts();

}  // namespace

uint64_t Checksum64(const void* data, size_t bytes, uint64_t seed) {
  ChecksumState state(seed);
  state.Update(data, bytes);
  return state.Finish();
}

namespace {

FileHeader HeaderOf(const Vocabulary& vocabulary) {
  FileHeader header{};
  std::memcpy(header.magic, kMagic, sizeof(kMagic));
  header.version = kFormatVersion;
  header.header_bytes = sizeof(FileHeader);
  header.branching = vocabulary.branching();
  header.depth = vocabulary.depth();
  header.scoring = static_cast<int32_t>(vocabulary.default_scoring());
  header.weighting = static_cast<int32_t>(vocabulary.weighting());
  header.node_count = vocabulary.node_count();
  header.word_count = vocabulary.word_count();
  header.block_bytes = vocabulary.memory_bytes();
  header.checksum = vocabulary.checksum();
  header.header_checksum = Checksum64(&header, kHeaderChecksummedBytes);
  return header;
}

}  // namespace

Status Vocabulary::SaveBinary(const std::string& path) const {
  const FileHeader header = HeaderOf(*this);
  return WriteFileAtomically(path, {{&header, sizeof(header)}, {block_, block_bytes_}})
      .WithContext("saving vocabulary");
}

std::string Vocabulary::SerializeBinary() const {
  const FileHeader header = HeaderOf(*this);
  std::string bytes(sizeof(header) + block_bytes_, '\0');
  std::memcpy(bytes.data(), &header, sizeof(header));
  std::memcpy(bytes.data() + sizeof(header), block_, block_bytes_);
  return bytes;
}

namespace {

// The checks of a binary vocabulary's header, for a file or buffer of `total_bytes` whose first
// `got` bytes were read into `header`.
Status CheckBinaryHeader(const FileHeader& header, size_t got, uint64_t total_bytes) {
  if (got < sizeof(kMagic) || std::memcmp(header.magic, kMagic, sizeof(kMagic)) != 0) {
    return Status::InvalidArgument("not a placedb binary vocabulary (bad magic)");
  }
  if (got < sizeof(header)) {
    return Status::Corruption("truncated header: the file has only " + std::to_string(total_bytes) +
                              " bytes");
  }
  if (header.version != kFormatVersion) {
    return Status::InvalidArgument("unsupported format version " + std::to_string(header.version) +
                                   " (this build reads " + std::to_string(kFormatVersion) + ")");
  }
  if (header.header_bytes != sizeof(FileHeader)) {
    return Status::Corruption("bad header size " + std::to_string(header.header_bytes));
  }
  if (Checksum64(&header, kHeaderChecksummedBytes) != header.header_checksum) {
    return Status::Corruption("header checksum mismatch");
  }
  if (header.branching < 2 || header.branching > 1024 || header.depth < 1 || header.depth > 32 ||
      header.scoring < 0 || header.scoring > 5 || header.weighting < 0 || header.weighting > 3) {
    return Status::Corruption("bad parameters in header: k " + std::to_string(header.branching) +
                              ", L " + std::to_string(header.depth) + ", scoring " +
                              std::to_string(header.scoring) + ", weighting " +
                              std::to_string(header.weighting));
  }
  if (header.node_count < 2 || header.word_count < 1 || header.word_count >= header.node_count ||
      header.node_count == Vocabulary::kNoWord) {
    return Status::Corruption("inconsistent counts: " + std::to_string(header.node_count) +
                              " nodes, " + std::to_string(header.word_count) + " words");
  }
  return Status::Ok();
}

}  // namespace

Status Vocabulary::CheckBlockSize(uint32_t node_count, uint32_t word_count, uint64_t block_bytes,
                                  uint64_t total_bytes) {
  const BlockLayout layout = LayoutFor(node_count, word_count);
  if (block_bytes != layout.total) {
    return Status::Corruption("block size " + std::to_string(block_bytes) + " does not match " +
                              std::to_string(node_count) + " nodes and " +
                              std::to_string(word_count) + " words (expected " +
                              std::to_string(layout.total) + ")");
  }
  const uint64_t expected_bytes = sizeof(FileHeader) + block_bytes;
  if (total_bytes < expected_bytes) {
    return Status::Corruption("truncated: the file has " + std::to_string(total_bytes) +
                              " bytes, the header announces " + std::to_string(expected_bytes));
  }
  if (total_bytes > expected_bytes) {
    return Status::Corruption("the file has " + std::to_string(total_bytes - expected_bytes) +
                              " unexpected trailing bytes");
  }
  return Status::Ok();
}

Result<std::shared_ptr<const Vocabulary>> Vocabulary::ParseBinary(std::string_view bytes) {
  FileHeader header{};
  const size_t got = std::min(bytes.size(), sizeof(header));
  if (got > 0) std::memcpy(&header, bytes.data(), got);  // an empty view may have no data
  PLACEDB_RETURN_IF_ERROR(CheckBinaryHeader(header, got, bytes.size()));
  PLACEDB_RETURN_IF_ERROR(
      CheckBlockSize(header.node_count, header.word_count, header.block_bytes, bytes.size()));
  auto allocated =
      Allocate(header.branching, header.depth, static_cast<ScoringType>(header.scoring),
               static_cast<WeightingType>(header.weighting), header.node_count, header.word_count,
               /*zero_fill=*/false);
  if (!allocated.ok()) return allocated.status();
  std::unique_ptr<Vocabulary> vocabulary = std::move(allocated).value();
  std::memcpy(vocabulary->block_, bytes.data() + sizeof(header), vocabulary->block_bytes_);
  const uint64_t checksum = Checksum64(vocabulary->block_, vocabulary->block_bytes_);
  if (checksum != header.checksum) {
    return Status::Corruption("checksum mismatch: the data is damaged");
  }
  PLACEDB_RETURN_IF_ERROR(vocabulary->ValidateBlock());
  vocabulary->checksum_ = checksum;
  return std::shared_ptr<const Vocabulary>(std::move(vocabulary));
}

Result<std::shared_ptr<const Vocabulary>> Vocabulary::LoadBinary(const std::string& path) {
  auto fail = [&path](const Status& status) {
    return status.WithContext("loading vocabulary " + path);
  };
  auto opened = OpenForReading(path);
  if (!opened.ok()) return fail(opened.status());
  FileDescriptor fd(*opened);
  struct stat info;
  if (::fstat(fd.get(), &info) != 0) return fail(Status::IoError(Errno("cannot stat", path)));
  const auto file_bytes = uint64_t(info.st_size);

  FileHeader header{};
  auto got = ReadFully(fd.get(), &header, sizeof(header), path);
  if (!got.ok()) return fail(got.status());
  const Status header_ok = CheckBinaryHeader(header, *got, file_bytes);
  if (!header_ok.ok()) return fail(header_ok);
  const Status size_ok =
      CheckBlockSize(header.node_count, header.word_count, header.block_bytes, file_bytes);
  if (!size_ok.ok()) return fail(size_ok);

  auto allocated =
      Allocate(header.branching, header.depth, static_cast<ScoringType>(header.scoring),
               static_cast<WeightingType>(header.weighting), header.node_count, header.word_count,
               /*zero_fill=*/false);
  if (!allocated.ok()) return fail(allocated.status());
  std::unique_ptr<Vocabulary> vocabulary = std::move(allocated).value();
  // Read and hash in chunks that fit in L2: the hash then costs no extra pass over memory.
  constexpr size_t kChunkBytes = size_t{1} << 20;
  static_assert(kChunkBytes % 32 == 0);
  ChecksumState state(0);
  for (size_t offset = 0; offset < vocabulary->block_bytes_; offset += kChunkBytes) {
    const size_t bytes = std::min(kChunkBytes, vocabulary->block_bytes_ - offset);
    got = ReadFully(fd.get(), vocabulary->block_ + offset, bytes, path);
    if (!got.ok()) return fail(got.status());
    if (*got != bytes) return fail(Status::Corruption("truncated while reading the block"));
    state.Update(vocabulary->block_ + offset, bytes);
  }
  const uint64_t checksum = state.Finish();
  if (checksum != header.checksum) {
    return fail(Status::Corruption("checksum mismatch: the data is damaged"));
  }
  PLACEDB_RETURN_IF_ERROR(vocabulary->ValidateBlock().WithContext("loading vocabulary " + path));
  vocabulary->checksum_ = checksum;
  return std::shared_ptr<const Vocabulary>(std::move(vocabulary));
}

Result<std::shared_ptr<const Vocabulary>> Vocabulary::ImportDbow2Text(const std::string& path) {
  const std::string context = "importing DBoW2 text vocabulary " + path;
  auto text = ReadWholeFile(path);
  if (!text.ok()) return text.status().WithContext(context);
  Result<VocabularyTree> tree = Status::Internal("unset");
  try {
    tree = ParseDbow2Text(*text);
  } catch (const std::bad_alloc&) {
    return Status::ResourceExhausted("out of memory").WithContext(context);
  }
  if (!tree.ok()) return tree.status().WithContext(context);
  text = std::string();  // free the text before laying out the tree
  auto vocabulary = FromTree(*tree);
  if (!vocabulary.ok()) {
    // The parser checked the structure; what is left (e.g. weights) is still the file's fault.
    return Status::Corruption(vocabulary.status().message()).WithContext(context);
  }
  return vocabulary;
}

std::vector<uint32_t> Vocabulary::TextExportOrder() const {
  // Lists nodes as late as the constraints allow: a leaf's line when its word is next, after
  // its ancestors and their earlier siblings (which every order must list first). A leaf that
  // has to be listed before its word is next proves that no order exists, so this finds an
  // order whenever there is one: DBoW2's files, depth-first or in sibling blocks, and
  // breadth-first trees alike.
  const std::vector<uint32_t> parent = Parents();
  std::vector<uint8_t> listed(node_count_, 0);
  std::vector<uint32_t> order;
  order.reserve(node_count_ > 0 ? node_count_ - 1 : 0);
  uint32_t next_word = 0;
  std::vector<uint32_t> path;
  while (next_word < word_count_) {
    path.clear();
    for (uint32_t node = word_node_[next_word]; node != 0; node = parent[node]) {
      path.push_back(node);
    }
    for (auto it = path.rbegin(); it != path.rend(); ++it) {
      for (uint32_t sibling = first_child_[parent[*it]]; sibling <= *it; ++sibling) {
        if (listed[sibling]) continue;
        listed[sibling] = 1;
        order.push_back(sibling);
        if (child_count_[sibling] == 0 && node_word_[sibling] != next_word++) return {};
      }
    }
  }
  if (order.size() + 1 != node_count_) return {};
  return order;
}

Status Vocabulary::ExportDbow2Text(const std::string& path) const {
  const std::string context = "exporting DBoW2 text vocabulary " + path;
  const std::vector<uint32_t> order = TextExportOrder();
  if (order.empty()) {
    return Status::FailedPrecondition(
               "its word ids are in an order that no DBoW2 text file can express (the format "
               "numbers words by the order of the leaf lines); save it as binary instead")
        .WithContext(context);
  }
  std::string out;
  try {
    out.reserve(size_t(node_count_) * 140 + 64);
    out += std::to_string(branching_) + ' ' + std::to_string(depth_) + ' ' +
           std::to_string(static_cast<int>(scoring_)) + ' ' +
           std::to_string(static_cast<int>(weighting_)) + '\n';
    const std::vector<uint32_t> parent = Parents();
    std::vector<uint32_t> line_of(node_count_, 0);  // the node's id in the file (root: 0)
    char number[64];
    for (size_t i = 0; i < order.size(); ++i) {
      const uint32_t node = order[i];
      line_of[node] = uint32_t(i + 1);
      const bool leaf = child_count_[node] == 0;
      char* end = std::to_chars(number, number + sizeof(number), line_of[parent[node]]).ptr;
      out.append(number, end);
      out += leaf ? " 1 " : " 0 ";
      const uint8_t* bytes = node_descriptor_[node].bytes();
      for (int b = 0; b < Descriptor256::kBytes; ++b) {
        const ByteText& entry = kByteTexts[bytes[b]];
        out.append(entry.text, entry.length);
      }
      // Shortest text that reads back as the same float: round trips are exact.
      const float weight = leaf ? word_weight_[node_word_[node]] : 0.0f;
      end = std::to_chars(number, number + sizeof(number), weight).ptr;
      out.append(number, end);
      out += '\n';
    }
  } catch (const std::bad_alloc&) {
    return Status::ResourceExhausted("out of memory").WithContext(context);
  }
  return WriteFileAtomically(path, {{out.data(), out.size()}}).WithContext(context);
}

Result<std::shared_ptr<const Vocabulary>> Vocabulary::Load(const std::string& path) {
  char magic[sizeof(kMagic)] = {};
  {
    auto opened = OpenForReading(path);
    if (!opened.ok()) return opened.status().WithContext("loading vocabulary " + path);
    FileDescriptor fd(*opened);
    auto got = ReadFully(fd.get(), magic, sizeof(magic), path);
    if (!got.ok()) return got.status().WithContext("loading vocabulary " + path);
  }
  if (std::memcmp(magic, kMagic, sizeof(kMagic)) == 0) return LoadBinary(path);
  return ImportDbow2Text(path);
}

}  // namespace placedb
