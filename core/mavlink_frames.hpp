// MAVLink framing for the link's per-datagram scan (mavlink_io/frame_scan.py is the reference): the
// frame lengths pymavlink counts, CRC-16/MCRF4XX (X.25) with CRC_EXTRA, and the walk that sets the
// unsigned, CRC-checked RAW_IMU frames of a read apart from the bytes left to pymavlink.
// Pure: no Python, no I/O.
#pragma once

#include <cstddef>
#include <cstdint>

namespace azimuthd {
namespace mavlink {

constexpr std::uint8_t MAGIC_V2 = 0xFD, MAGIC_V1 = 0xFE, IFLAG_SIGNED = 0x01;
constexpr std::uint8_t RAW_IMU_ID = 27, RAW_IMU_CRC_EXTRA = 144;
constexpr std::size_t HEADER_V2 = 10;

// CRC-16/MCRF4XX (poly 0x1021 reflected = 0x8408, no final xor), MAVLink's crc_accumulate:
//   tmp = b ^ (crc & 0xff); tmp ^= tmp << 4; crc = (crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)
inline std::uint16_t crc_accumulate(std::uint8_t b, std::uint16_t crc) {
    std::uint8_t tmp = static_cast<std::uint8_t>(b ^ static_cast<std::uint8_t>(crc & 0xFF));
    tmp = static_cast<std::uint8_t>(tmp ^ static_cast<std::uint8_t>(tmp << 4));
    return static_cast<std::uint16_t>((crc >> 8) ^ (static_cast<std::uint16_t>(tmp) << 8) ^
                                      (static_cast<std::uint16_t>(tmp) << 3) ^ (tmp >> 4));
}

inline std::uint16_t crc_x25(const std::uint8_t* p, std::size_t n, std::uint16_t crc = 0xFFFF) {
    for (std::size_t i = 0; i < n; ++i) crc = crc_accumulate(p[i], crc);
    return crc;
}

// A RAW_IMU frame taken by the scan: header fields and where its payload lies in the read.
struct RawImuSpan {
    std::uint8_t src_system, src_component, seq;
    std::size_t payload_at, payload_len;
};

// frame_scan.split_raw_imu: walk a read (pymavlink's parser holding nothing before it) frame by frame
// with pymavlink's framing rules (v2: len + 12, + 13 signed; v1: len + 8; a frame is consumed whole
// whatever its CRC; non-magic bytes up to the next magic byte are one bad prefix; a frame cut by the
// end stays with pymavlink). ``segment(from, to)`` gets the bytes left to pymavlink, ``frame(span)``
// each unsigned MAVLink 2 RAW_IMU whose CRC (over header and payload, then CRC_EXTRA) matches, in order;
// segments are never merged across a taken frame.
template <class Segment, class Frame>
void split_raw_imu(const std::uint8_t* d, std::size_t n, Segment&& segment, Frame&& frame) {
    std::size_t pos = 0, seg = 0;
    while (pos < n) {
        const std::uint8_t b = d[pos];
        if (b != MAGIC_V2 && b != MAGIC_V1) {  // bad prefix: up to the next magic byte
            ++pos;
            while (pos < n && d[pos] != MAGIC_V2 && d[pos] != MAGIC_V1) ++pos;
            continue;
        }
        if (pos + 3 > n) break;  // length unknown: pymavlink holds it
        const std::size_t plen = d[pos + 1];
        const std::size_t length =
            b == MAGIC_V2 ? plen + 12 + ((d[pos + 2] & IFLAG_SIGNED) ? 13 : 0) : plen + 8;
        if (pos + length > n) break;  // cut by the end of the read: pymavlink holds it
        if (b == MAGIC_V2 && d[pos + 2] == 0 && d[pos + 7] == RAW_IMU_ID && d[pos + 8] == 0 &&
            d[pos + 9] == 0) {
            const std::size_t end = pos + HEADER_V2 + plen;
            const std::uint16_t crc = crc_accumulate(RAW_IMU_CRC_EXTRA, crc_x25(d + pos + 1, end - pos - 1));
            if (crc == static_cast<std::uint16_t>(d[end] | (d[end + 1] << 8))) {
                if (seg < pos) segment(seg, pos);
                frame(RawImuSpan{d[pos + 5], d[pos + 6], d[pos + 4], pos + HEADER_V2, plen});
                seg = pos + length;
            }
        }
        pos += length;
    }
    if (seg < n) segment(seg, n);
}

}  // namespace mavlink
}  // namespace azimuthd
