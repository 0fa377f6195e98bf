// Follows the presenter's camera smoothly: each new pose becomes a goal that the
// camera eases towards over a few frames (turning about the target, not cutting
// through the model), then the animation stops -- rendering stays on demand.

import * as THREE from 'three';

const TAU = 0.15; // seconds for ~63 % of the way: smooth, yet a fraction of a second behind

export class CameraFollower {
	constructor( viewer ) {
		this.viewer = viewer;
		this.goal = null;
		this.running = false;
	}

	// pose: {position, target, up} in patient LPS mm.
	follow( pose ) {
		const v = this.viewer;
		this.goal = {
			position: v.toWorld( pose.position ),
			target: v.toWorld( pose.target ),
			up: v.lpsDirectionToWorld( pose.up ),
		};
		if ( this.running ) return;
		this.running = true;
		this.last = performance.now();
		requestAnimationFrame( ( t ) => this.step( t ) );
	}

	stop() {
		this.goal = null;
	}

	step( now ) {
		const goal = this.goal;
		if ( ! goal ) {
			this.running = false;
			return;
		}
		const v = this.viewer;
		const k = 1 - Math.exp( - Math.min( 0.1, ( now - this.last ) / 1000 ) / TAU );
		this.last = now;
		const target = v.controls.target.clone().lerp( goal.target, k );
		const from = v.camera.position.clone().sub( v.controls.target );
		const to = goal.position.clone().sub( goal.target );
		const turn = new THREE.Quaternion().setFromUnitVectors( from.clone().normalize(), to.clone().normalize() );
		const offset = from.clone().normalize().applyQuaternion( new THREE.Quaternion().slerp( turn, k ) );
		offset.multiplyScalar( THREE.MathUtils.lerp( from.length(), to.length(), k ) );
		const up = v.camera.up.clone().lerp( goal.up, k ).normalize();
		const done = offset.angleTo( to ) < 1e-3 && target.distanceTo( goal.target ) < 1e-4 * to.length();
		if ( done ) {
			v.setWorldPose( goal.position, goal.target, goal.up );
			this.goal = null;
			this.running = false;
			return;
		}
		v.setWorldPose( target.clone().add( offset ), target, up );
		requestAnimationFrame( ( t ) => this.step( t ) );
	}
}
