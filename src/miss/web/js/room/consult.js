// The live consultation on a model: joins its room and ties the room's messages
// to the viewer (pins, pointers, measurements, the presenter's camera) and to
// the side panel (people, tools, lists, chat). One instance per page.

import { Annotations } from './annotations.js';
import { CameraFollower } from './follow.js';
import { RoomClient } from './room.js';
import { RoomPanel } from './room-panel.js';
import { PointerTools } from './tools.js';
import { status } from '../test-hooks.js';
import { addressViews } from '../viewer/deep-link.js';

// What the server's close codes mean, in words for the panel.
const CLOSED = {
	1008: 'Disconnected: too many messages were sent.',
	1013: 'Disconnected: the connection was too slow for the room; reload to rejoin.',
	4401: 'Not allowed in: log in again, or check the link.',
	4403: 'This link lets you view the model but not join the consultation.',
	4404: 'This model has no room you may enter.',
	4410: 'The share link has expired or was revoked.',
};

export class Consultation {
	// structures: the page's StructuresPanel, whose parts shown and clipping the room shares.
	// volume: the page's VolumePanel (null where the scan is not offered), its view shared too.
	// slices: the page's LinkedSlices (null where the scan is not offered): on or off and the crosshair.
	// signedIn: the name of a colleague signed in on this server who opened a share link.
	constructor( { viewer, modelId, container, share = '', guest = false, structures = null, volume = null, slices = null, signedIn = null } ) {
		this.viewer = viewer;
		this.structures = structures;
		this.volume = volume;
		this.slices = slices;
		const asked = addressViews();
		this.addressView = asked.has( 'volume' );
		this.addressSlices = asked.has( 'slices' );
		this.modelId = modelId;
		this.annotations = new Annotations( viewer );
		this.follower = new CameraFollower( viewer );
		this.state = { you: null, people: new Map(), presenter: null, following: true, pins: new Map(), measurements: new Map(), chat: [], errors: [], connected: false };
		const name = guest ? localStorage.getItem( 'miss.guestName' ) || signedIn || 'Guest' : '';
		this.room = new RoomClient( modelId, { share, name } );
		this.panel = new RoomPanel( container, this.handlers(), { guest, guestName: name } );
		this.bindRoom();
		this.tools = new PointerTools( this );
		viewer.onCameraChange( () => this.isPresenting() && this.sendCamera() );
		if ( structures ) structures.onChange = () => this.sendDisplay();
		if ( volume ) {
			volume.onChange = () => {
				this.addressView = false;
				this.sendDisplay();
			};
		}
		if ( slices ) {
			slices.onChange = () => {
				this.addressSlices = false;
				this.sendDisplay();
			};
		}
		this.publish();
		this.room.connect();
	}

	isPresenting() {
		return this.state.you && this.state.presenter === this.state.you.id;
	}

	// What shows is the presenter's to set, or the owner's while nobody presents.
	setsDisplay() {
		const s = this.state;
		return Boolean( s.you && ( this.isPresenting() || ( s.you.owner && ! s.presenter ) ) );
	}

	sendDisplay() {
		if ( ! this.setsDisplay() ) return;
		const was = this.state.display;
		this.state.display = { ...this.structures.display(), volume: this.volume?.state() ?? was?.volume ?? null,
			slices: this.slices?.state() ?? was?.slices ?? null };
		this.room.throttled( 'display', { type: 'display', ...this.state.display }, 150 );
	}

	// The scan's view too, except that an address asking for one (?view=, a deep link) keeps
	// it until the room's next change.
	showDisplay() {
		if ( ! this.state.display || ! this.viewer.model ) return;
		this.structures?.applyDisplay( this.state.display );
		if ( ! this.addressView ) this.volume?.apply( this.state.display.volume ).catch( () => {} );
		if ( ! this.addressSlices ) this.slices?.apply( this.state.display.slices ).catch( () => {} );
		this.slices?.redraw(); // the parts shown and the clipping cut the outlines too
	}

	sendCamera() {
		this.room.throttled( 'camera', { type: 'camera', ...this.viewer.pose() }, 70 );
	}

	// What browser tests read (window.__miss.room): a plain snapshot.
	publish() {
		const s = this.state;
		status.room = {
			connected: s.connected, you: s.you, presenter: s.presenter, following: this.followingNow(),
			participants: [ ...s.people.values() ], pins: [ ...s.pins.values() ],
			measurements: [ ...s.measurements.values() ], chat: [ ...s.chat ], errors: [ ...s.errors ],
			closed: s.closed || null,
		};
	}

	followingNow() {
		const s = this.state;
		return Boolean( s.following && s.presenter && s.you && s.presenter !== s.you.id );
	}

	mine( item ) {
		const you = this.state.you;
		return Boolean( you && ( item.by === you.key || you.owner ) );
	}

	handlers() {
		return {
			present: ( on ) => this.room.send( { type: 'presenter', on } ),
			follow: ( on ) => {
				this.state.following = on;
				this.updateFollow();
				this.catchUp();
			},
			tool: ( tool ) => this.tools.setTool( tool ),
			pin: ( note ) => this.tools.placePin( note ),
			cancelPin: () => this.tools.setTool( 'pin' ),
			chat: ( text ) => this.room.send( { type: 'chat', text } ),
			removePin: ( id ) => this.room.send( { type: 'unpin', id } ),
			removeMeasurement: ( id ) => this.room.send( { type: 'unmeasure', id } ),
			goto: ( item ) => this.lookAt( item.point ),
			rename: ( name ) => {
				localStorage.setItem( 'miss.guestName', name || 'Guest' );
				this.room.name = name || 'Guest'; // for a reconnection
				this.room.send( { type: 'rename', name: name || 'Guest' } ); // one event, not leave + join
			},
		};
	}

	// Turns the view (locally) to face a point from the current distance.
	lookAt( lps ) {
		const v = this.viewer;
		const target = v.toWorld( lps );
		const offset = v.camera.position.clone().sub( v.controls.target );
		v.setWorldPose( target.clone().add( offset ), target, v.camera.up );
		if ( this.isPresenting() ) this.sendCamera();
	}

	updateFollow() {
		const s = this.state;
		const following = this.followingNow();
		this.viewer.controls.enabled = ! following;
		if ( ! following ) this.follower.stop();
		const presenter = s.people.get( s.presenter );
		let text = 'Free view: nobody is presenting.';
		if ( this.isPresenting() ) text = 'You are presenting: the others follow your view.';
		else if ( following ) text = `Following ${presenter ? presenter.name : 'the presenter'}.`;
		else if ( s.presenter ) text = `Free view (${presenter ? presenter.name : 'someone'} is presenting).`;
		this.panel.setFollowState( text );
		this.publish();
	}

	refreshPeople() {
		const s = this.state;
		this.panel.setParticipants( [ ...s.people.values() ], s.presenter, s.you?.id );
		this.updateFollow();
	}

	refreshPins() {
		const pins = [ ...this.state.pins.values() ];
		this.annotations.setPins( pins );
		this.panel.setPins( pins, ( p ) => this.mine( p ) );
		this.publish();
	}

	refreshMeasurements() {
		const items = [ ...this.state.measurements.values() ];
		this.annotations.setMeasurements( items );
		this.panel.setMeasurements( items, ( m ) => this.mine( m ) );
		this.publish();
	}

	refreshChat() {
		this.panel.setChat( this.state.chat );
		this.publish();
	}

	// After the model (re)loads, its scale may differ: redraw what is on it, and
	// take up the presenter's view again (loading framed the model anew).
	modelLoaded() {
		this.annotations.refresh();
		this.showDisplay();
		this.catchUp();
	}

	catchUp() {
		if ( this.followingNow() && this.state.view && this.viewer.model ) this.follower.follow( this.state.view );
	}

	bindRoom() {
		const s = this.state;
		const room = this.room;
		room.on( 'open', () => {
			s.connected = true;
			s.closed = null;
			this.panel.setStatus( 'connected' );
			this.panel.showError( '' );
			this.publish();
		} );
		room.on( 'welcome', ( m ) => this.welcome( m ) );
		this.bindPresence();
		this.bindItems();
		room.on( 'error', ( m ) => {
			s.errors.push( m );
			this.panel.showError( m.error );
			this.publish();
		} );
		room.on( 'closed', ( m ) => {
			s.connected = false;
			this.panel.setStatus( m.final ? 'closed' : 'reconnecting…' );
			if ( m.final ) this.panel.showError( CLOSED[ m.code ] || m.reason || 'The room closed the connection.' );
			s.closed = m;
			this.publish();
		} );
	}

	// Who is here, who presents, where they look and point.
	bindPresence() {
		const s = this.state;
		const room = this.room;
		room.on( 'joined', ( m ) => {
			s.people.set( m.participant.id, m.participant );
			this.refreshPeople();
		} );
		room.on( 'renamed', ( m ) => {
			s.people.set( m.participant.id, m.participant );
			if ( s.you?.id === m.participant.id ) s.you = { ...s.you, name: m.participant.name };
			this.refreshPeople();
		} );
		room.on( 'left', ( m ) => {
			s.people.delete( m.id );
			this.annotations.laser( m.id, null, null );
			this.refreshPeople();
		} );
		room.on( 'presenter', ( m ) => {
			if ( m.id !== s.presenter ) s.view = null;
			s.presenter = m.id;
			this.refreshPeople();
			if ( this.isPresenting() ) this.sendCamera();
		} );
		room.on( 'camera', ( m ) => {
			if ( m.from !== s.presenter ) return;
			s.view = m;
			if ( this.followingNow() ) this.follower.follow( m );
		} );
		room.on( 'laser', ( m ) => this.annotations.laser( m.from, m.colour, m.point ) );
		room.on( 'display', ( m ) => {
			this.state.display = m.item;
			this.addressView = this.addressSlices = false;
			this.showDisplay();
		} );
	}

	bindItems() {
		const s = this.state;
		const room = this.room;
		room.on( 'pin', ( m ) => {
			s.pins.set( m.item.id, m.item );
			this.refreshPins();
		} );
		room.on( 'unpin', ( m ) => {
			s.pins.delete( m.id );
			this.refreshPins();
		} );
		room.on( 'measure', ( m ) => {
			s.measurements.set( m.item.id, m.item );
			this.refreshMeasurements();
		} );
		room.on( 'unmeasure', ( m ) => {
			s.measurements.delete( m.id );
			this.refreshMeasurements();
		} );
		room.on( 'chat', ( m ) => {
			s.chat.push( m.item );
			this.refreshChat();
		} );
	}

	welcome( m ) {
		const s = this.state;
		s.you = m.you;
		s.people = new Map( m.participants.map( ( p ) => [ p.id, p ] ) );
		s.presenter = m.presenter;
		s.pins = new Map( m.pins.map( ( p ) => [ p.id, p ] ) );
		s.measurements = new Map( m.measurements.map( ( x ) => [ x.id, x ] ) );
		s.chat = m.chat;
		s.view = m.view;
		s.display = m.display;
		this.showDisplay(); // what the owner or presenter left showing, after a reload too
		this.panel.setStatus( `connected as ${m.you.name}` );
		this.refreshPeople();
		this.refreshPins();
		this.refreshMeasurements();
		this.refreshChat();
		this.catchUp(); // a late joiner sees what the presenter shows now
	}
}
