import base64, json, urllib.request, cv2, numpy as np, sys
def b64(p): return base64.b64encode(open(p,'rb').read()).decode()
cam=json.load(open('/tmp/hC/cap1/camera.json'))
def post(body):
    req=urllib.request.Request("http://127.0.0.1:8799/estimate", json.dumps(body).encode(), {"Content-Type":"application/json"})
    try: a=json.load(urllib.request.urlopen(req, timeout=120)); return 200,a
    except urllib.error.HTTPError as e: return e.code, json.load(e)
base={"rgb_png_b64":b64('/tmp/hC/cap1/rgb.png'),"depth_png_b64":b64('/tmp/hC/cap1/depth.png'),"step":2}
I=[1,0,0,0,1,0,0,0,1]
c,a=post(dict(base, camera=dict(cam, cam_R_w2c=I, cam_t_w2c=[0.29,0.71,0.5]), box=[297,184,389,268])); print('metres:',c,a.get('error'))
c,a=post(dict(base, camera=cam, box=[297,184,700,268])); print('past edge:',c,a.get('ok'),a.get('confident'),'mask:',a.get('mask'))
c,a=post(dict(base, camera=cam, box=[297,184,389,268], hand_eye={"T_robot_camera":np.eye(4).tolist()}, pick_box=[100,100,200,200], pick_point=[500,400])); print('pick_box+pick_point:',c,a.get('error') or (a.get('ok'), {k:v for k,v in a.items() if 'pick' in k}))
