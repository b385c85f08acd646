# markhold as a BlueOS extension: the field build (`run`, `preflight`, `replay`,
# `params check`; no simulator, no Aravis) on Debian 12 with Debian's OpenCV 4.6, with
# its web page on port 8780 (BlueOS's sidebar, Cockpit's widget).
# Three platforms: linux/arm/v7 (BlueOS as Blue Robotics ships it on the Raspberry Pi 4),
# linux/arm64 (a 64-bit Pi OS) and linux/amd64 (a desktop or an x86 companion):
#   docker buildx build --platform linux/arm/v7,linux/arm64,linux/amd64 -t USER/markhold:TAG --push .
# How to install it in BlueOS and what the labels mean: docs/blueos-extension.md.

FROM debian:bookworm AS build
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
       ca-certificates curl build-essential pkg-config libopencv-dev libclang-dev clang \
       libgstreamer1.0-dev libgstreamer-plugins-base1.0-dev \
    && rm -rf /var/lib/apt/lists/*
# The toolchain the project is tested with (rust-version in Cargo.toml is the floor), for
# the image's own userland (Debian's architecture: armhf for linux/arm/v7, arm64,
# amd64), not guessed from the kernel: an arm/v7 image built on a 64-bit ARM kernel
# would otherwise get an aarch64 toolchain it cannot run.
ARG RUST_VERSION=1.95.0
RUN arch="$(dpkg --print-architecture)" \
    && case "${arch}" in \
      amd64) host=x86_64-unknown-linux-gnu ;; \
      arm64) host=aarch64-unknown-linux-gnu ;; \
      armhf) host=armv7-unknown-linux-gnueabihf ;; \
      *) echo "markhold: Debian ${arch} is not built (linux/arm/v7, linux/arm64, linux/amd64)" >&2; exit 1 ;; \
    esac \
    && curl -sSf https://sh.rustup.rs | sh -s -- -y --profile minimal \
       --default-host "${host}" --default-toolchain "${RUST_VERSION}"
ENV PATH=/root/.cargo/bin:$PATH
WORKDIR /src
COPY . .
# Field features only: not `sim` (the simulator) and not `genicam` (Aravis). Two jobs, no
# debug info and no incremental state: less memory and disk for the build (a 32-bit rustc
# on arm/v7 has at most 4 GB of address space; the opencv crate is the largest unit).
ARG MARKHOLD_FEATURES=""
ENV CARGO_BUILD_JOBS=2 CARGO_PROFILE_RELEASE_DEBUG=0 CARGO_INCREMENTAL=0
RUN cargo build --release --locked -p markhold --no-default-features --features "${MARKHOLD_FEATURES}" \
    && cp target/release/markhold /usr/local/bin/markhold \
    && strip /usr/local/bin/markhold

FROM debian:bookworm-slim
# OpenCV 4.6 runtime libraries for the modules markhold links (core, imgproc, calib3d,
# aruco from contrib, imgcodecs, videoio); GStreamer for the stock camera's H.264 stream
# (udp/rtp/rtsp from -good, h264parse from -bad, avdec_h264 from -libav).
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
       libopencv-core406 libopencv-imgproc406 libopencv-calib3d406 libopencv-contrib406 \
       libopencv-imgcodecs406 libopencv-videoio406 \
       gstreamer1.0-plugins-base gstreamer1.0-plugins-good gstreamer1.0-plugins-bad gstreamer1.0-libav \
    && rm -rf /var/lib/apt/lists/*
COPY --from=build /usr/local/bin/markhold /usr/local/bin/markhold
COPY blueos/entrypoint.sh /usr/local/bin/markhold-extension
COPY params /usr/share/markhold/params
COPY docs/blueos-extension.md docs/first-dive.md /usr/share/doc/markhold/

# Where the extension's readme and docs are published (the copy you build from).
ARG REPO_RAW_URL=https://raw.githubusercontent.com/OWNER/markhold/main
LABEL version="0.1.0"
LABEL type="tool"
LABEL tags='["positioning", "navigation", "camera", "station-keeping"]'
LABEL company='{"about": "Station keeping on a fiducial marker for ArduSub vehicles", "name": "markhold", "email": ""}'
LABEL authors='[{"name": "markhold developers", "email": ""}]'
LABEL readme="${REPO_RAW_URL}/docs/blueos-extension.md"
LABEL links="{\"documentation\": \"${REPO_RAW_URL}/docs/first-dive.md\", \"website\": \"${REPO_RAW_URL}/README.md\"}"
LABEL requirements="core >= 1.1"
# Host networking (the MAVLink router's TCP server is on 127.0.0.1:5777 of the Pi; the
# web page on 0.0.0.0:8780, where BlueOS's helper finds it; the Foxglove live view on
# 0.0.0.0:8765) and the V4L2 cameras (character major 81) through /dev;
# /usr/blueos/extensions/markhold holds the site file and the recordings. With host
# networking a port needs no binding (Docker discards PortBindings then): ExposedPorts
# names the page's and the live view's ports.
EXPOSE 8780/tcp 8765/tcp
LABEL permissions='{"ExposedPorts": {"8780/tcp": {}, "8765/tcp": {}}, "HostConfig": {"NetworkMode": "host", "Binds": ["/dev:/dev:rw", "/usr/blueos/extensions/markhold:/data:rw"], "DeviceCgroupRules": ["c 81:* rmw"], "RestartPolicy": {"Name": "unless-stopped"}}}'

ENTRYPOINT ["/usr/local/bin/markhold-extension"]
