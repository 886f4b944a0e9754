// Offline driver for OpenRatSLAM's C++ core (davidmball/ratslam, src/ratslam), written for mapserver's
// differential harness. This file is ours; it only #includes OpenRatSLAM's headers, which the harness
// finds in a local copy given on the command line (nothing of OpenRatSLAM is stored in this repository).
//
// It reproduces the ROS nodes' call order per camera frame (main_lv, main_pc, main_em):
//   image    -> LocalViewMatch::on_image -> PosecellNetwork::on_view_template(id, relative_rad)
//   odometry -> src = current_exp_id; PosecellNetwork::on_odo(v, w, dt); action = get_action()
//            -> ExperienceMap::on_odo(v, w, dt)
//            -> per action: CREATE_NODE: on_create_experience(dest); on_set_experience(dest, 0)
//                           CREATE_EDGE: on_create_link(src, dest, rad); on_set_experience(dest, rad)
//                           SET_NODE:    on_set_experience(dest, rad)
//               and ExperienceMap::iterate() after every published action (never on NO_ACTION).
// Differences from a ROS run, chosen so that both engines see the same inputs: the odometry arrives as
// one message per frame (the motion integrated since the previous frame) and the first one is not dropped.
//
// Input (little-endian): "RSLF" u32 version=1, u32 frames, u32 width, u32 height, u32 channels (1 or 3);
// then per frame: f64 stamp_s, f64 vtrans_m_s, f64 vrot_rad_s, f64 dt_s, width*height*channels u8 pixels.
// Output: OUT/trace.csv (one row per frame), OUT/experiences.csv, OUT/links.csv, timing on stdout.
#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdlib>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <boost/property_tree/ini_parser.hpp>

#include "ratslam/experience_map.h"
#include "ratslam/local_view_match.h"
#include "ratslam/posecell_network.h"

namespace {

struct Header {
  char magic[4];
  uint32_t version, frames, width, height, channels;
};

struct Odo {
  double stamp, vtrans, vrot, dt;
};

bool read_header(std::ifstream &in, Header &h) {
  in.read(h.magic, 4);
  in.read(reinterpret_cast<char *>(&h.version), 5 * sizeof(uint32_t));
  return in && std::string(h.magic, 4) == "RSLF" && h.version == 1 && (h.channels == 1 || h.channels == 3);
}

void write_map(const std::string &out, ratslam::ExperienceMap &em) {
  std::ofstream e(out + "/experiences.csv");
  e.precision(17);
  e << "id,x_m,y_m,th_rad\n";
  for (int i = 0; i < em.get_num_experiences(); i++) {
    ratslam::Experience *x = em.get_experience(i);
    e << x->id << ',' << x->x_m << ',' << x->y_m << ',' << x->th_rad << '\n';
  }
  std::ofstream l(out + "/links.csv");
  l.precision(17);
  l << "from,to,d,heading_rad,facing_rad,delta_time_s\n";
  for (int i = 0; i < em.get_num_links(); i++) {
    ratslam::Link *k = em.get_link(i);
    l << k->exp_from_id << ',' << k->exp_to_id << ',' << k->d << ',' << k->heading_rad << ',' << k->facing_rad
      << ',' << k->delta_time_s << '\n';
  }
}

}  // namespace

int main(int argc, char **argv) {
  if (argc != 4) {
    std::cerr << "usage: driver CONFIG.ini FRAMES.bin OUTDIR" << std::endl;
    return 2;
  }
  boost::property_tree::ptree settings, rs;
  boost::property_tree::read_ini(argv[1], settings);
  rs = settings.get_child("ratslam");
  std::ifstream in(argv[2], std::ios::binary);
  Header h;
  if (!read_header(in, h)) {
    std::cerr << argv[2] << ": not a frames file (RSLF v1)" << std::endl;
    return 2;
  }
  const size_t npix = size_t(h.width) * h.height * h.channels;
  std::vector<Odo> odo(h.frames);
  std::vector<std::vector<unsigned char>> images(h.frames, std::vector<unsigned char>(npix));
  for (uint32_t f = 0; f < h.frames; f++) {
    in.read(reinterpret_cast<char *>(&odo[f]), sizeof(Odo));
    in.read(reinterpret_cast<char *>(images[f].data()), npix);
  }
  if (!in) {
    std::cerr << argv[2] << ": truncated" << std::endl;
    return 2;
  }
  // OpenRatSLAM prints a line per frame and per default setting; keep stdout for our summary.
  std::streambuf *saved = std::cout.rdbuf();
  std::ofstream devnull("/dev/null");
  std::cout.rdbuf(devnull.rdbuf());

  ratslam::LocalViewMatch lv(rs);
  ratslam::PosecellNetwork pc(rs);
  ratslam::ExperienceMap em(rs);
  struct Row {
    int vt;
    double lv_rad;
    int action, src, dest, exp;
    double px, py, pth;
  };
  std::vector<Row> rows(h.frames);
  const bool grey = h.channels == 1;
  int templates = 0;
  // RATSLAM_DUMP_FRAME=N: write the pose-cell activity after frame N to OUT/cells_N.bin (float64, θ-major).
  const char *dump_env = std::getenv("RATSLAM_DUMP_FRAME");
  const long dump_frame = dump_env ? std::atol(dump_env) : -1;
  auto t0 = std::chrono::steady_clock::now();
  for (uint32_t f = 0; f < h.frames; f++) {
    lv.on_image(images[f].data(), grey, h.width, h.height);
    pc.on_view_template(lv.get_current_vt(), lv.get_relative_rad());
    const Odo &o = odo[f];
    const int src = pc.get_current_exp_id();
    pc.on_odo(o.vtrans, o.vrot, o.dt);
    const int action = pc.get_action();
    em.on_odo(o.vtrans, o.vrot, o.dt);
    const int dest = pc.get_current_exp_id();
    const double rad = pc.get_relative_rad();
    if (action == ratslam::PosecellNetwork::CREATE_NODE) {
      em.on_create_experience(dest);
      em.on_set_experience(dest, 0);
    } else if (action == ratslam::PosecellNetwork::CREATE_EDGE) {
      em.on_create_link(src, dest, rad);
      em.on_set_experience(dest, rad);
    } else if (action == ratslam::PosecellNetwork::SET_NODE) {
      em.on_set_experience(dest, rad);
    }
    if (action != ratslam::PosecellNetwork::NO_ACTION) em.iterate();
    if ((long)f == dump_frame) {
      std::ofstream d(std::string(argv[3]) + "/cells_" + std::to_string(f) + ".bin", std::ios::binary);
      const int dim_xy = rs.get<int>("pc_dim_xy", 21), dim_th = rs.get<int>("pc_dim_th", 36);
      d.write(reinterpret_cast<const char *>(pc.get_cells()), sizeof(double) * dim_xy * dim_xy * dim_th);
    }
    templates = std::max(templates, lv.get_current_vt() + 1);
    rows[f] = {lv.get_current_vt(), lv.get_relative_rad(), action, src, dest, em.get_current_id(),
               pc.x(), pc.y(), pc.th()};
  }
  double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::cout.rdbuf(saved);

  const std::string out = argv[3];
  std::ofstream t(out + "/trace.csv");
  t.precision(17);
  t << "frame,template,lv_relative_rad,action,src,dest,experience,pc_x,pc_y,pc_th\n";
  for (uint32_t f = 0; f < h.frames; f++) {
    const Row &r = rows[f];
    t << f << ',' << r.vt << ',' << r.lv_rad << ',' << r.action << ',' << r.src << ',' << r.dest << ',' << r.exp
      << ',' << r.px << ',' << r.py << ',' << r.pth << '\n';
  }
  write_map(out, em);
  std::printf("frames=%u experiences=%d links=%d templates=%d slam_seconds=%.6f frames_per_s=%.1f\n", h.frames,
              em.get_num_experiences(), em.get_num_links(), templates, seconds,
              h.frames / seconds);
  return 0;
}
